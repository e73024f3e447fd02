# Two commands: `make run` and `make test`. Both create .venv and install everything pinned.
# If a ROS 2 Jazzy is sourced (rclpy importable), the venv sees it and the PyPI ROS wheels
# are not installed; otherwise they are. Over a sourced Jazzy the 'numpy1' pins keep its
# numpy 1.26 (an OpenCV 5 wheel would pull numpy 2 into the venv and shadow it).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: run test venv weights bench clean

run: $(STAMP)
	$(PY) -m activeloc_ros.bringup $(ARGS)

test: $(STAMP)
	$(PY) -m pytest -q test $(PYTEST_ARGS)

venv: $(STAMP)

$(STAMP): setup.py
	@if $(PYTHON) -c 'import rclpy' 2>/dev/null; then \
	    echo 'using the sourced ROS 2 (rclpy found)'; \
	    $(PYTHON) -m venv --system-site-packages $(VENV); EXTRAS=numpy1,test; \
	else \
	    $(PYTHON) -m venv $(VENV); EXTRAS=ros,numpy2,test; \
	fi; \
	$(PY) -m pip install -q --upgrade pip && \
	$(PY) -m pip install -q torch==2.13.0 && \
	$(PY) -m pip install -q -e ".[$$EXTRAS]"
	$(PY) -m activeloc_ros.perception.weights fetch
	touch $(STAMP)

weights: $(STAMP)

clean:
	rm -rf $(VENV) build install log *.egg-info
