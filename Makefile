# The two commands of README.md: `make run` and `make test` (`make docs` builds the manual into var/site).  Both
# create the virtual environment (.venv) on first use and re-install only when pyproject.toml changes.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
AXE := var/node/node_modules/axe-core/axe.min.js
# MathJax for the manual's formulas; a prefix of its own, since npm prunes what it did not just install.
MATHJAX := var/node-docs/node_modules/mathjax/es5/tex-svg.js
# pytest-xdist worker processes for `make test`: one more than the cores, since the tests spend part of their time
# waiting on the browsers, servers and Dask workers they start (2 cores, 2026-12-06: -n 2 435 s, -n 3 373 s with the
# CPU idle 1.9 % of the run, -n 4 415 s; docs/writing-docs.md).  `make test TEST_WORKERS=0` runs serially.
TEST_WORKERS ?= $(shell echo $$(( $$(nproc) + 1 )))

.PHONY: install run test lint docs clean

$(STAMP): pyproject.toml
	@# Debian's python3 lacks venv/ensurepip unless python3-venv is installed.
	@$(PYTHON) -c "import ensurepip, venv" 2>/dev/null || { \
		echo "installing python3-venv (apt-get)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3 python3-venv python3-pip; }
	@# OSMesa renders on the CPU (no GPU, no display); libGL for PyOpenGL.
	@ldconfig -p | grep -q libOSMesa.so && ldconfig -p | grep -q 'libGL.so.1' || { \
		echo "installing libosmesa6 libgl1 (apt-get)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libosmesa6 libgl1; }
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,docs]'
	$(BIN)/python -m pip install --quiet --no-deps pyrender==0.1.45
	@touch $(STAMP)

install: $(STAMP)

run: $(STAMP)
	$(BIN)/animstudy clips build --out var/clips
	$(BIN)/animstudy render --clips var/clips --out var/media
	$(BIN)/animstudy serve --host 127.0.0.1 --port 8000

lint: $(STAMP)
	$(BIN)/ruff check .

# Strict: a broken link or anchor, or a page in the nav missing from docs/, fails.  Offline: the theme fetches no
# fonts, no plugin downloads anything; only MathJax comes from the npm registry, once, and the site works without it.
docs: $(STAMP)
	@test -f $(MATHJAX) || { command -v npm >/dev/null && npm install --no-save --no-audit --no-fund \
		--prefix var/node-docs mathjax@3; } || echo "note: MathJax not installed; formulas show as TeX source"
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet

test: lint
	@# The browser tests drive Debian's Chromium through Playwright (never a downloaded browser).
	@test -x /usr/bin/chromium || { echo "installing chromium (apt-get)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; }
	@# axe-core 4 (the accessibility checker the browser tests inject) from the npm registry, once, into var/.
	@command -v npm >/dev/null || { echo "installing npm (apt-get)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq npm; }
	@test -f $(AXE) || npm install --no-save --no-audit --no-fund --prefix var/node axe-core@4
	@$(MAKE) --no-print-directory docs
	@# In parallel (pytest-xdist, TEST_WORKERS processes, whole files per worker so that module fixtures are built
	@# once; the files with the most `slow` tests first, so that the run ends on short ones: tests/conftest.py and
	@# --no-loadscope-reorder; each worker has its own databases and var dir, see tests/conftest.py), then the tests marked `serial`
	@# (PostgreSQL stopped for everyone) alone, collected from the files that mark any (a test marked `serial` in a
	@# file that does not say `mark.serial` would be missed: tests/conftest.py stops the collection then); exit
	@# status 5 there is "none selected" (no TEST_DATABASE_URL).
	@# Both steps share one directory for what a run builds once (tests/conftest.py, once_per_run). Bytecode is
	@# written even where the environment says not to (PYTHONDONTWRITEBYTECODE, set on these machines): the suite starts
	@# dozens of Python processes (commands, Dask workers, servers), each of which would compile the project anew.
	@start=$$(date +%s); rc=0; unset PYTHONDONTWRITEBYTECODE; \
	export ANIMSTUDY_TEST_RUN_DIR=$$(mktemp -d -t animstudy-test-run-XXXXXX); \
	trap 'rm -rf "$$ANIMSTUDY_TEST_RUN_DIR"' EXIT; \
	echo "$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder -m 'not serial'"; \
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder -m 'not serial' --durations=15 || rc=$$?; \
	parallel=$$(( $$(date +%s) - start )); \
	serial=$$(grep -l 'mark\.serial' tests/test_*.py); \
	echo "$(BIN)/python -m pytest -p no:xdist -m serial" $$serial; \
	$(BIN)/python -m pytest -p no:xdist -m serial $$serial || { s=$$?; test $$s -eq 5 || rc=$$s; }; \
	total=$$(( $$(date +%s) - start )); \
	printf 'make test: pytest took %dm%02ds (parallel step %dm%02ds with -n %s, serial step %dm%02ds)\n' \
		$$((total / 60)) $$((total % 60)) $$((parallel / 60)) $$((parallel % 60)) "$(TEST_WORKERS)" \
		$$(((total - parallel) / 60)) $$(((total - parallel) % 60)); \
	exit $$rc

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache *.egg-info var/site
