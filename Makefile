# handkse: `make demo` runs the main job, `make test` runs the tests; both set everything up.
#
# Installs come from the committed lock (requirements/dev.lock, with hashes): pip installs exactly
# the locked versions, then the project itself without resolving anything. `make lock` regenerates
# the locks from pyproject.toml; `make test-latest` runs the suite against the newest releases in a
# throw-away venv, to see drift coming before a new user does.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
# Extras installed for development; the lock covers exactly these (plus the build tools).
EXTRAS ?= dev,eval,robot,detector,tune,view,realsense
LOCK   := requirements/dev.lock
STAMP  := $(VENV)/.installed
PIP    := $(BIN)/python -m pip --disable-pip-version-check
# uv from the venv once installed; a uv on PATH before that.
UV     ?= $(shell test -x $(BIN)/uv && echo $(BIN)/uv || echo uv)
UV_COMPILE := $(UV) pip compile --quiet --generate-hashes --no-header
LATEST := .venv-latest

.PHONY: install demo test test-latest lint lock bench clean

install: $(STAMP)

$(STAMP): pyproject.toml $(LOCK)
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else "handkse needs Python 3.10 or newer")'
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet --require-hashes --no-deps -r $(LOCK)
	$(PIP) install --quiet --no-deps --no-build-isolation -e .
	$(PIP) check
	$(BIN)/handkse models prepare
	@touch $(STAMP)

demo: install
	$(BIN)/handkse demo

lint: install
	$(BIN)/ruff check --no-cache services tests bench

# Regenerate every lock from pyproject.toml. dev.lock is universal (Python 3.10-3.12, markers
# pick each Python's versions); the image locks are for the images' Python and platform and are
# constrained by dev.lock, so a package shared by the venv and an image has the same version.
lock:
	$(UV_COMPILE) --universal --python-version 3.10 -c requirements/constraints.txt \
	  pyproject.toml requirements/build.in \
	  $(foreach e,$(subst $(comma), ,$(EXTRAS)),--extra $(e)) -o $(LOCK)
	$(UV_COMPILE) --python-version 3.11 --python-platform x86_64-manylinux_2_28 \
	  -c $(LOCK) pyproject.toml requirements/build.in --extra robot --extra detector --extra realsense \
	  -o requirements/cpu.lock
	$(UV_COMPILE) --python-version 3.11 --python-platform x86_64-manylinux_2_28 \
	  -c $(LOCK) pyproject.toml requirements/build.in --extra gpu --extra realsense \
	  -o requirements/gpu.lock

comma := ,

# As root on a machine without them (a fresh Debian CI runner), install the system tools the
# tests use: ip (network namespaces) and openssl (TLS certificates) for the deployment tests,
# chromium for the web viewer test, libusb for pyrealsense2. Otherwise those tests skip with the
# reason.
SYSTEM_TOOLS := ip:iproute2 openssl:openssl chromium:chromium
SYSTEM_LIBS  := libusb-1.0.so.0:libusb-1.0-0
test: install lint
	@missing=""; for t in $(SYSTEM_TOOLS); do command -v $${t%%:*} >/dev/null || missing="$$missing $${t#*:}"; done; \
	for t in $(SYSTEM_LIBS); do ldconfig -p | grep -q "$${t%%:*}" || missing="$$missing $${t#*:}"; done; \
	if [ -n "$$missing" ] && [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo "installing$$missing"; \
	  apt-get update -qq && apt-get install -y -qq --no-install-recommends $$missing; fi
	$(BIN)/python -m pytest -q

# The suite against the newest releases pyproject.toml allows, in a throw-away venv.
test-latest:
	rm -rf $(LATEST)
	$(PYTHON) -m venv $(LATEST)
	$(LATEST)/bin/python -m pip install --quiet --upgrade pip
	$(LATEST)/bin/python -m pip install --quiet --upgrade -e '.[$(EXTRAS)]'
	$(LATEST)/bin/python -m pip list --format=freeze > $(LATEST)/versions.txt
	$(LATEST)/bin/handkse models prepare
	HANDKSE_DEPENDENCIES=latest $(LATEST)/bin/python -m pytest -q -p no:cacheprovider
	rm -rf $(LATEST)

bench: install
	$(BIN)/python -m bench.run all

clean:
	rm -rf $(VENV) $(LATEST) .pytest_cache .ruff_cache .hypothesis
