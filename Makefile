# zeus_ros: `make demo` and `make test` do all set-up themselves (make setup).
SHELL := /bin/bash
.SHELLFLAGS := -eo pipefail -c

# DDS discovery never leaves this machine (scripts/ros_env.sh sets the same).
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export RMW_IMPLEMENTATION := rmw_fastrtps_cpp

# A shell with the venv, the ROS env and the colcon install overlay.
IN_WS := source scripts/ros_env.sh && source "$$ZEUS_VENV/bin/activate" && source install/setup.bash &&

.PHONY: setup test test-unit demo lint bench clean

setup:
	bash scripts/setup.sh

test: setup
	$(IN_WS) python -m pytest -q test

# The ROS-free tests alone (a minute or so); `make test` runs these and the ros ones.
test-unit: setup
	$(IN_WS) python -m pytest -q -m unit test

# The target-velocity cheetah (cheetah-run-v1), where a context is needed by
# construction: up-osi (the best learned context measured there), whose
# decoded target follows each swap up and down, beside the context-free
# reference (sac) through the same graph. DEMO_WEIGHTS=weights/cheetah-run-v1-zeus-id
# shows this project's zeus-id instead. The friction walker:
# DEMO_WEIGHTS=weights/walker-walk-slippery-zeus
# DEMO_REFERENCE=weights/walker-walk-slippery-sac DEMO_SCHEDULE=0:0.25,333:0.06,666:0.5
DEMO_WEIGHTS ?= weights/cheetah-run-v1-up-osi
DEMO_REFERENCE ?= $(wildcard weights/cheetah-run-v1-sac)
DEMO_SCHEDULE ?= 0:0.5,333:2.5,666:1.2
demo: setup
	$(IN_WS) python -m zeus_ros.demo --weights $(DEMO_WEIGHTS) --out demo_out \
	  --schedule $(DEMO_SCHEDULE) $(if $(DEMO_REFERENCE),--reference-weights $(DEMO_REFERENCE))

lint: setup
	$(IN_WS) ruff check .

clean:
	rm -rf build install log demo_out

# Benchmarks (see BENCHMARKS.md). REALTIME_SECONDS=600 for the 10-minute realtime goal.
REALTIME_SECONDS ?= 60
# The trainer's speed is reported as a ratio to this commit (issue 13's starting point).
TRAINER_BASELINE ?= ad864f5
bench: setup
	$(IN_WS) python bench/bench_hop.py
	$(IN_WS) python bench/bench_loop.py --weights weights/walker-walk-v0-zeus --composed \
	  --transports SHM \
	  --realtime-weights weights/cheetah-run-v0-zeus --realtime-seconds $(REALTIME_SECONDS) \
	  --compare-normal-scheduler --json bench/results_loop.json
	$(IN_WS) python bench/bench_trainer.py --profile cpu --threads 2 1
	$(IN_WS) python bench/bench_trainer_ab.py --baseline $(TRAINER_BASELINE) --rounds 3 --threads 1 \
	  --pair --json bench/results_trainer_ab.json

# Soak (issue 17): lockstep loop, a live swap every 10 s, a kill -9 and restart
# of each node; figures per minute and the goals' pass/fail (bench/soak.py).
# Exits non-zero when a goal is missed. SOAK_MINUTES=30 for the recorded run.
SOAK_MINUTES ?= 30
.PHONY: soak
soak: setup
	$(IN_WS) python bench/soak.py --minutes $(SOAK_MINUTES) --json bench/results_soak.json
