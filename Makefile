# handkse: `make demo` runs the main job, `make test` runs the tests; both set everything up.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
EXTRAS ?= dev,eval,robot,detector
STAMP  := $(VENV)/.installed

.PHONY: install demo test lint bench clean

install: $(STAMP)

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else "handkse needs Python 3.10 or newer")'
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[$(EXTRAS)]'
	$(BIN)/handkse models prepare
	@touch $(STAMP)

demo: install
	$(BIN)/handkse demo

lint: install
	$(BIN)/ruff check --no-cache services tests bench

# As root on a machine without them (a fresh Debian CI runner), install the system tools the
# deployment tests use: ip (network namespaces) and openssl (TLS certificates). Otherwise those
# tests skip with the reason.
test: install lint
	@if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
	    { ! command -v ip >/dev/null || ! command -v openssl >/dev/null; }; then \
	  apt-get update -qq && apt-get install -y -qq --no-install-recommends iproute2 openssl; fi
	$(BIN)/python -m pytest -q

bench: install
	$(BIN)/python -m bench.run all

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .hypothesis
