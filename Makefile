# Two commands on a fresh machine: `make demo` and `make test`. Both set up .venv when missing.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
XVFB_PKGS := xvfb xauth libxkbcommon-x11-0 libxcb-icccm4 libxcb-image0 libxcb-keysyms1 \
	libxcb-randr0 libxcb-render-util0 libxcb-xinerama0 libxcb-xfixes0 libxcb-shape0 \
	libxcb-cursor0 libegl1 libgl1 libglib2.0-0 libfontconfig1 libdbus-1-3

.PHONY: setup test demo xvfb clean

setup: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	@$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "Python >= 3.11 is needed"' || { echo "napari-fdlc needs Python >= 3.11 (set PYTHON=...)"; exit 1; }
	@# a venv left without pip (python3-venv missing the first time) is made again
	$(PY) -m pip --version >/dev/null 2>&1 || $(PYTHON) -m venv --clear $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e '.[napari,test]'
	touch $(STAMP)

# Xvfb gives napari a real X server with OpenGL for the GUI tests and the headless demo.
# Installed only when missing and when we are root; otherwise the GUI tests skip with a reason.
xvfb:
	@if ! command -v xvfb-run >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "Installing Xvfb and Qt's X11 libraries (Debian packages)..."; \
	    (apt-get install -y -qq $(XVFB_PKGS) >/dev/null 2>&1 || \
	     (apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq $(XVFB_PKGS) >/dev/null)) || \
	    echo "Could not install Xvfb: GUI tests will be skipped."; \
	  else echo "Xvfb is missing and we are not root: GUI tests will be skipped."; fi; \
	fi

test: setup xvfb
	@if command -v xvfb-run >/dev/null 2>&1; then \
	  xvfb-run -a -s "-screen 0 1600x1000x24" $(PY) -m pytest -q tests; \
	else \
	  FDLC_NO_DISPLAY=1 $(PY) -m pytest -q tests; \
	fi

demo: setup xvfb
	$(PY) -m napari_fdlc.demo

clean:
	rm -rf $(VENV) build src/*.egg-info demo_output
