# The two set-up commands of README.md: `make run` and `make test`.  Both create the virtual environment
# (.venv) on first use and re-install only when pyproject.toml changes.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
AXE := var/node/node_modules/axe-core/axe.min.js

.PHONY: install run test lint clean

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
	$(BIN)/python -m pip install --quiet -e '.[test]'
	$(BIN)/python -m pip install --quiet --no-deps pyrender==0.1.45
	@touch $(STAMP)

install: $(STAMP)

run: $(STAMP)
	$(BIN)/animstudy clips build --out var/clips
	$(BIN)/animstudy render --clips var/clips --out var/media
	$(BIN)/animstudy serve --host 127.0.0.1 --port 8000

lint: $(STAMP)
	$(BIN)/ruff check .

test: lint
	@# The browser tests drive Debian's Chromium through Playwright (never a downloaded browser).
	@test -x /usr/bin/chromium || { echo "installing chromium (apt-get)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; }
	@# axe-core 4 (the accessibility checker the browser tests inject) from the npm registry, once, into var/.
	@command -v npm >/dev/null || { echo "installing npm (apt-get)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq npm; }
	@test -f $(AXE) || npm install --no-save --no-audit --no-fund --prefix var/node axe-core@4
	$(BIN)/python -m pytest

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache *.egg-info
