# The two commands of the README:
#   make demo   set up, then run the main job on the built-in sample scene
#   make test   set up (with ROS + chromium for their tests), then run the whole test suite
PY := .venv/bin/python
DEMO_OUT ?= out/demo

.PHONY: setup setup-test demo test bench

setup:
	@scripts/setup.sh

setup-test:
	@scripts/setup.sh --test-system

demo: setup
	$(PY) -m presim demo $(DEMO_OUT)

test: setup-test
	$(PY) -m pytest -q --durations=20

bench: setup
	$(PY) benchmarks/run_all.py
