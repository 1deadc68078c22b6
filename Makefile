# FroDO workspace commands. `make demo` and `make test` work on a fresh machine (they run setup first).
VENV ?= .venv
PY := $(VENV)/bin/python
DEMO_BAG ?= bags/demo_walk.mcap
DEMO_OUT ?= out/demo
PYTEST_ARGS ?=

.PHONY: setup demo test test-fast colcon clean

setup:
	bash scripts/setup.sh

demo: setup
	$(VENV)/bin/frodo demo --bag $(DEMO_BAG) --out $(DEMO_OUT)

test: setup
	$(PY) -m pytest -p no:cacheprovider -q $(PYTEST_ARGS) src tests

colcon: setup
	bash scripts/colcon_check.sh

clean:
	rm -rf build install log out .pytest_cache
