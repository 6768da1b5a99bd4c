"""The one rule for tests that need a real Prosody: skip when it is not installed, unless CI says it
must be there (QUEKARO_REQUIRE_PROSODY=1, set by .ci/run), in which case the test runs and fails."""

from __future__ import annotations

import os
import shutil

import pytest

PROSODY_MISSING = shutil.which("prosody") is None or shutil.which("openssl") is None

needs_prosody = pytest.mark.skipif(
    PROSODY_MISSING and not os.environ.get("QUEKARO_REQUIRE_PROSODY"),
    reason="prosody/openssl not installed (Debian packages prosody, openssl)")
