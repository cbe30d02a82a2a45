# bearing_loc_ros: two entry points for a fresh machine, `make demo` and `make test`.
# Everything is installed into .venv from PyPI; nothing installed by hand is needed.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export AMENT_PREFIX_PATH := $(CURDIR)/$(VENV)
export PYTHONDONTWRITEBYTECODE := 1

.PHONY: all venv test browser demo bench clean

all: test

venv: $(STAMP)

$(STAMP): requirements.txt setup.py package.xml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip 2>&1 | grep -v 'is ignored' || true
	$(PY) -m pip install -q -r requirements.txt 2>&1 | grep -v 'is ignored' ; test $${PIPESTATUS[0]} -eq 0
	$(PY) -m pip install -q -e . 2>&1 | grep -v 'is ignored' ; test $${PIPESTATUS[0]} -eq 0
	$(PY) -c 'import rclpy, numpy, scipy, yaml, geometry_msgs.msg'
	$(PY) -m bearing_loc_ros.core.warmup
	touch $(STAMP)

test: $(STAMP) browser
	$(PY) -m pytest test -q -p no:cacheprovider

# Headless Chromium for the map page test (test/test_gis_browser.py): installed with apt-get
# when running as root on Debian/Ubuntu; elsewhere that test skips and says why.
browser:
	@command -v chromium >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium) \
	  >/dev/null 2>&1; } || echo 'chromium not installed: the map browser test will be skipped'

demo: $(STAMP)
	$(PY) -m bearing_loc_ros.demo

bench: $(STAMP)
	for f in bench/*.py; do echo "== $$f"; $(PY) $$f || exit 1; done

clean:
	rm -rf $(VENV) build install log demo_out
