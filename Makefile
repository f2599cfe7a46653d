# Two entry points do all the set-up on a fresh machine:
#   make demo   -- create .venv, install, run the main job on the small CPU default
#   make test   -- create .venv, install, run the test suite
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test test-fast bench install clean gl-deps

install: $(STAMP)

# torch is installed first and exactly, so that no looser spec pulls CUDA wheels. The development
# install includes the optional Meta-World extra, so that the tests cover the faucet tasks, and
# the stats extra, so that they compare the report's aggregates with rliable's, the wandb extra,
# so that they read back what a run logs to Weights & Biases offline, and the hub extra, so that
# they check what `dvfb push` refuses and says against a stand-in hub on a loopback port. The
# stamp follows this file too: an extra added here is installed into an existing .venv.
$(STAMP): pyproject.toml Makefile
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[dev,metaworld,stats,wandb,hub]'
	touch $(STAMP)

# The GIF of the demo renders with OpenGL: gl-deps installs software OpenGL when it is missing.
demo: $(STAMP) gl-deps
	$(VENV)/bin/dvfb demo

# pytest-xdist workers. The SLURM tests stay together on one worker (tests/conftest.py), which
# mostly waits for the cluster, so the full suite takes a third worker on two cores; the fast tier
# is all computation and takes one per core.
TEST_WORKERS ?= 3
FAST_WORKERS ?= 2
test: $(STAMP) gl-deps
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadgroup

# The development tier: everything but the SLURM cluster, the end-to-end pipelines and the slow tests.
test-fast: $(STAMP) gl-deps
	$(PY) -m pytest -q -n $(FAST_WORKERS) --dist loadgroup -m 'not slurm and not e2e and not slow'

# Software OpenGL (OSMesa) for the rendering tests of `dvfb video` (tests/test_analysis.py).
# Installed from Debian's libosmesa6 when missing and we are root; otherwise the test says how.
gl-deps:
	@if ldconfig -p 2>/dev/null | grep -q 'libOSMesa\.so'; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	  echo "installing libosmesa6 (software OpenGL for the video tests)"; \
	  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libosmesa6 >/dev/null 2>&1 || \
	  { apt-get update -qq >/dev/null 2>&1 && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libosmesa6 >/dev/null 2>&1; } || \
	  echo "warning: could not install libosmesa6; the video tests will fail (apt-get install -y libosmesa6)"; \
	else \
	  echo "note: libOSMesa is missing and cannot be installed here (not root); the video tests need it: apt-get install -y libosmesa6"; \
	fi

bench: $(STAMP)
	$(PY) bench/run.py

clean:
	rm -rf $(VENV) runs demo
