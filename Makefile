# Two entry points from a fresh clone: `make demo` and `make test`. Each makes its own venv.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-$(shell cksum pyproject.toml | cut -d' ' -f1)

.PHONY: demo test bench core-check clean screenshots golden docs docs-serve figures

$(STAMP): pyproject.toml
	@# the viewer tests drive Lichtblick in Debian's chromium (Playwright from PyPI, no browser download)
	command -v chromium >/dev/null || (apt-get update -qq && apt-get install -y -qq chromium >/dev/null)
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	rm -f $(VENV)/.installed-*; touch $@

demo: $(STAMP)
	$(VENV)/bin/stack-fleet run scenarios/four-robot-diamond.yaml --out runs/demo

test: $(STAMP)
	$(PY) -m pytest -q --durations=25

# the README's viewer pictures, taken by the viewer tests from the real viewer (Lichtblick in chromium)
screenshots: $(STAMP)
	STACK_SHOTS=docs/figures $(PY) -m pytest -q tests/test_viewer.py

# the documentation site (docs/, mkdocs.yml) into site/, strict: a broken link or reference fails it
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs build --strict

docs-serve: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs serve

# every figure in docs/ made again from runs (bench/figures.py --list says which command makes which; hours)
figures: $(STAMP)
	$(PY) -m pip install -q -e '.[test,bench]'
	$(PY) bench/figures.py

# the golden step logs (tests/golden/, tests/test_replay.py) recorded again: after a change meant to alter decisions
golden: $(STAMP)
	$(PY) tests/golden_logs.py

bench: $(STAMP)
	$(PY) -m pip install -q -e '.[test,bench]'
	$(PY) bench/fleet_bench.py

# What a robot installs: the core package alone in a fresh venv (no simulator, no torch), then the agent's help.
core-check:
	rm -rf .venv-core && python3 -m venv .venv-core
	.venv-core/bin/python -m pip install -q .
	.venv-core/bin/python -m pip list --format=freeze | grep -iE '^(pybullet|torch|matplotlib|tqdm)=' || true
	.venv-core/bin/stack-agent --help >/dev/null && echo "core install: stack-agent --help runs"

clean:
	rm -rf $(VENV) .venv-core runs site
