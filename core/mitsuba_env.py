"""Mitsuba set-up for one process: pick the variant (llvm first, scalar as a logged fallback), the
Dr.Jit thread count, and Mitsuba's log on stderr. Every process that renders calls `init` before
loading a scene."""

from __future__ import annotations

import logging
import os
import sys
from typing import Any

from core.errors import QuekaroError, RenderError, did_you_mean

# Mitsuba and Dr.Jit are imported where used: `import mitsuba` costs ~0.35 s and 85 MB, must follow the
# variant choice (core.mitsuba_env), and processes that never render must not pay for it.

log = logging.getLogger(__name__)

DEFAULT_VARIANT = "llvm_ad_rgb"
THREADS_ENV = "QUEKARO_THREADS"

_state: dict[str, object] = {"variant": None, "requested": None, "threads": None}


def scalar_equivalent(variant: str) -> str:
    """The scalar variant computing the same colours as `variant` (llvm_ad_rgb -> scalar_rgb)."""
    for prefix in ("llvm_ad_", "cuda_ad_", "llvm_", "cuda_"):
        if variant.startswith(prefix):
            return "scalar_" + variant[len(prefix):]
    return variant


def threads_from_env() -> int | None:
    """The thread count asked for in QUEKARO_THREADS, or None when unset."""
    raw = os.environ.get(THREADS_ENV, "").strip()
    if not raw:
        return None
    try:
        value = int(raw)
    except ValueError:
        raise QuekaroError(f"{THREADS_ENV}={raw!r} is not an integer") from None
    if value < 1:
        raise QuekaroError(f"{THREADS_ENV}={raw!r} must be at least 1")
    return value


def _llvm_usable() -> bool:
    import drjit as dr

    # Without a usable libLLVM, Dr.Jit imports fine but reports no LLVM backend.
    return bool(dr.has_backend(dr.JitBackend.LLVM))


def _select_variant(variant: str) -> str:
    import mitsuba as mi

    available = mi.variants()
    if variant not in available:
        raise QuekaroError(f"Mitsuba variant {variant!r} is not available{did_you_mean(variant, available)} "
                           f"(have: {', '.join(available)})")
    if variant.startswith("llvm_"):
        reason = None
        try:
            mi.set_variant(variant)
            if not _llvm_usable():
                reason = "Dr.Jit found no usable LLVM backend (install libllvm19)"
        except Exception as exc:  # an unloadable libLLVM surfaces as ImportError or RuntimeError
            reason = f"{type(exc).__name__}: {exc}"
        if reason is None:
            return variant
        fallback = scalar_equivalent(variant)
        if fallback not in available:
            raise QuekaroError(f"Mitsuba variant {variant!r} cannot load ({reason}); no scalar fallback")
        log.warning("Mitsuba variant %s cannot load (%s): falling back to %s, 2.5-5x slower",
                    variant, reason, fallback)
        variant = fallback
    try:
        mi.set_variant(variant)
    except (ImportError, RuntimeError) as exc:  # e.g. a cuda variant on a machine without a usable GPU
        raise QuekaroError(f"Mitsuba variant {variant!r} cannot load here ({type(exc).__name__}: {exc})") from exc
    return variant


def require_vectorised(what: str) -> None:
    """Raise RenderError unless this process renders with a vectorised variant (llvm or cuda): `what`
    traces Dr.Jit wavefronts, which a scalar variant (the fallback without LLVM) does not have."""
    import mitsuba as mi

    variant = mi.variant() or ""
    if variant.startswith("scalar_"):
        why = (f"the fallback for {_state['requested']}, whose LLVM backend did not load (install libllvm19)"
               if _state["requested"] != variant else "as asked")
        raise RenderError(f"{what} needs an llvm_* or cuda_* Mitsuba variant; this process renders with "
                          f"{variant} ({why}). Level off renders in any variant")


def init(variant: str = DEFAULT_VARIANT, threads: int | None = None) -> str:
    """Set the Mitsuba variant and Dr.Jit's thread count; return the variant actually in use.

    `threads=None` takes QUEKARO_THREADS, else leaves Dr.Jit's default (one per core). Calling it
    again with the same arguments does nothing; with another variant it switches.
    """
    import drjit as dr

    if threads is None:
        threads = threads_from_env()
    if threads is not None and threads < 1:
        raise QuekaroError(f"thread count must be at least 1, got {threads}")
    import mitsuba as mi

    _logs_to_stderr(mi)
    # Re-select when asked for another variant, or when someone switched it behind our back.
    if _state["requested"] != variant or mi.variant() != _state["variant"]:
        _state["variant"] = _select_variant(variant)
        _state["requested"] = variant
    if threads is not None and _state["threads"] != threads:
        dr.set_thread_count(threads)
        _state["threads"] = threads
    return str(_state["variant"])


def _logs_to_stderr(mi: Any) -> None:
    """Send Mitsuba's log (its warnings: a film format overridden, an unused parameter) to stderr, once
    per process: its own appender writes to stdout, where `--json` commands print their JSON."""
    if _state.get("log"):
        return

    class ToStderr(mi.Appender):
        def append(self, level: Any, text: str) -> None:
            sys.stderr.write(text + "\n")

        def log_progress(self, *args: Any) -> None:
            pass  # quekaro shows its own progress

    logger = mi.logger()
    logger.clear_appenders()
    logger.add_appender(ToStderr())
    _state["log"] = True


def current_variant() -> str | None:
    """The variant chosen by the last `init`, or None before the first one."""
    return _state["variant"]  # type: ignore[return-value]
