# Both entry points bootstrap .venv from nothing on a fresh machine.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: run test bench lint clean paper

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,plot,postgres]'
	touch $(STAMP)

# The browser panel on loopback (docs/panel.md): the daemon prints its URL, with the token, at start.
WEB ?= 8790
# A second one beside it: make run STATE_DIR=/tmp/rig2 SOCKET=/tmp/rig2.sock WEB=8791
run: $(STAMP)
	$(VENV)/bin/usmswitchd --sim --web $(WEB) $(if $(STATE_DIR),--state-dir $(STATE_DIR)) $(if $(SOCKET),--socket $(SOCKET))

# The suite, the soaks and the benches start ~1,000 Python processes (daemons, their server
# processes, usmswitchctl): where PYTHONDONTWRITEBYTECODE is set (the machine of these figures sets
# it), each compiled every module it imported from source again, and pytest rewrote every test
# file in each of its processes (collection 9 s of CPU a process, 3 s with the cache): about a sixth
# of the suite's CPU. These targets let Python keep its __pycache__ (git ignores it), its default.
test bench soak: export PYTHONDONTWRITEBYTECODE =

# Two processes, a test file each at a time (module fixtures made once); `pytest FILE` runs one alone.
test: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadfile

# BENCH=predictor runs benchmarks/bench_predictor.py only.
bench: $(STAMP)
	$(PY) -m benchmarks $(BENCH)

# The paper's experiments on the simulated rig and the report beside the paper (runs/paper-<time>/).
paper: $(STAMP)
	$(VENV)/bin/usmswitch-experiment all --out runs/paper-$$(date +%Y%m%d-%H%M%S)

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

clean:
	rm -rf $(VENV) build *.egg-info

# The MCU firmware (firmware/): avr-gcc image + simavr harness; `make flash PORT=/dev/ttyACM0`.
.PHONY: firmware flash soak
firmware:
	$(MAKE) -C firmware firmware

# The soaks: the firmware's (tests/firmware/soak.py: 100,000 strokes in simavr, every stamp and
# drive-off against the harness's truth, then the soak must catch a planted one-period stamp error)
# and the daemon loop's (100,000 strokes in virtual time, every one in SQLite, memory flat): ~4 min.
soak: $(STAMP)
	USMSWITCH_SOAK_STROKES=100000 USMSWITCH_SOAK_PLANT=1 $(PY) -m pytest tests/firmware/test_soak.py -q -s -rs
	$(PY) -m pytest -m soak -q -s -rs

flash:
	$(MAKE) -C firmware flash PORT=$(PORT)
