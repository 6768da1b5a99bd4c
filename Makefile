# One entry point for set-up, the demo and the tests. Each target does its own set-up.
PY ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: setup system-deps demo test lint bench clean docs-figures

# Debian packages: libllvm19 for Mitsuba's llvm variants, prosody (+ openssl for its certificates) for the
# multi-host XMPP server and its tests, chromium + chromium-driver for the web page's browser tests, iproute2
# (network namespaces) and faketime (an agent's clock 10 minutes off) for the multi-host tests, python3 (the
# system's, which a second local user can run) for the hostile-local-user test.
system-deps:
	@need=""; \
	[ -e /usr/lib/x86_64-linux-gnu/libLLVM-19.so.1 ] || [ -e /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 ] || ls /usr/lib/*/libLLVM*19* >/dev/null 2>&1 || need="$$need libllvm19"; \
	command -v prosody >/dev/null 2>&1 || need="$$need prosody"; \
	command -v openssl >/dev/null 2>&1 || need="$$need openssl"; \
	command -v ip >/dev/null 2>&1 || need="$$need iproute2"; \
	[ -x /usr/bin/python3 ] || need="$$need python3"; \
	ls /usr/lib/*/faketime/libfaketimeMT.so.1 >/dev/null 2>&1 || need="$$need faketime"; \
	[ -x /usr/bin/chromium ] || need="$$need chromium"; \
	[ -x /usr/bin/chromedriver ] || need="$$need chromium-driver"; \
	command -v dockerd >/dev/null 2>&1 || need="$$need docker.io"; \
	command -v debootstrap >/dev/null 2>&1 || need="$$need debootstrap"; \
	if [ -n "$$need" ]; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    echo "installing Debian packages:$$need"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$need >/dev/null; \
	    systemctl disable --now prosody >/dev/null 2>&1 || service prosody stop >/dev/null 2>&1 || true; \
	    case "$$need" in *docker.io*) systemctl disable --now docker.socket docker.service >/dev/null 2>&1 \
	      || service docker stop >/dev/null 2>&1 || true;; esac; \
	  else \
	    echo "missing Debian packages:$$need (run 'sudo apt-get install$$need'); Mitsuba falls back to scalar_rgb without libllvm19"; \
	  fi; \
	fi

$(BIN)/quekaro: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	@touch $@

setup: system-deps $(BIN)/quekaro

demo: setup
	$(BIN)/quekaro demo

# The suite's files on TEST_WORKERS processes (pytest-xdist, a file's tests together on one: its farm is
# made once), in the order collected (tests/conftest.py: the longest files first). Most of the suite waits on
# farms, servers and browsers; two share this machine's two cores.
# Then the tests marked `alone`, with the machine to themselves.
TEST_WORKERS ?= 2

test: setup
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q -m "not alone" -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder --durations=25
	$(BIN)/python -m pytest -q -m alone --durations=5

lint: setup
	$(BIN)/ruff check .

# docs/benchmarks/README.md's figure blocks, copied again from the files the benchmarks wrote, and the
# README's figure (docs/benchmarks/curves.png) drawn again from the accuracy reports.
docs-figures: setup
	$(BIN)/python -m bench.docs
	$(BIN)/python -m bench.curves

# docs/benchmarks/README.md's figure files written again by the commands that wrote them (each report's
# .provenance.json), then its blocks refreshed: the stale ones (planned with another rule file than the shipped one), or
# every one with BENCH=--all (BENCH=--dry-run lists the commands). Hours; run it alone on the machine.
bench: setup
	$(BIN)/python -m bench.rerun $(BENCH)

clean:
	rm -rf $(VENV) out var .pytest_cache .ruff_cache
