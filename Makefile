# Slipstream: `make demo` runs the main job, `make test` runs every check. Both set up .venv.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml | md5sum | cut -c1-12)
ARTIFACTS ?= artifacts
# STRICT=1: a test that would skip for lack of bubblewrap, PostgreSQL, Chromium or an extra
# fails instead (CI=true, as .ci/run runs, does the same).
STRICT ?=

.PHONY: system install lint typecheck test demo bench mutate clean

# System packages, installed with apt-get only when missing: bubblewrap (the submission
# sandbox), chromium (browser tests of the website), postgresql (migration tests).
system:
	@missing=""; \
	[ -x /usr/bin/bwrap ] || missing="$$missing bubblewrap"; \
	[ -x /usr/bin/chromium ] || missing="$$missing chromium"; \
	ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || missing="$$missing postgresql"; \
	if [ -n "$$missing" ]; then \
	  echo "apt-get install:$$missing"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -q && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -q $$missing; \
	fi

$(PY):
	python3 -m venv $(VENV)

# torch first and pinned: it takes the CPU build; an unpinned torch pulls GBs of CUDA wheels.
$(STAMP): pyproject.toml | $(PY)
	$(PIP) install -q --upgrade pip
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e '.[train,eval,server,dev,rllib]'
	rm -f $(VENV)/.installed-* && touch $@

install: system $(STAMP)

lint: install
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/ruff check .

typecheck: install
	$(VENV)/bin/mypy

test: install lint typecheck
	mkdir -p $(ARTIFACTS)
	SLIPSTREAM_STRICT=$(STRICT) $(VENV)/bin/pytest -n 2 -q --durations=25 --doctest-modules tracks arena agents submissions leaderboard tests

# The main job: a leaderboard seeded with the baselines and the shipped checkpoint, a batch of
# sandboxed races run by a local worker, served on http://127.0.0.1:8000 (Ctrl-C stops it).
demo: install
	mkdir -p $(ARTIFACTS)/demo
	$(VENV)/bin/slipstream demo --data-dir $(ARTIFACTS)/demo/site --races 12 --workers 2 --port 8000

# Figures, not tests: each script prints a table (and --json). Run on a quiet machine.
bench: install
	$(PY) bench/track_speed.py
	$(PY) bench/env_speed.py
	$(PY) bench/batch_speed.py
	$(PY) bench/sandbox_overhead.py
	$(PY) bench/race_throughput.py
	$(PY) bench/leaderboard_load.py

# Mutation testing of the critical modules ([tool.mutmut] in pyproject.toml): slow, not part of
# `make test`. Module by module (shortest first), one child process (the machine is shared;
# MUTATE_JOBS=2 on a quiet one). Each run re-tests every mutant it names; mutants/ keeps the
# results (and mutmut's test timings) for the report, `rm -rf mutants` starts afresh.
# MUTATE="arena.rewards.*" runs one module. The sandbox is scoped to its policy decisions
# (which mode, which limits, which identity and paths the fallback gets): its mechanisms are
# pinned by the hostile suite, whose sandboxed races take seconds per mutant. Then the report:
# the score per module and every survivor with its verdict (bench/mutation_verdicts.json).
# One OpenMP/MKL thread: mutmut forks its children from a process that has imported torch, and
# a forked child whose parent had started torch's thread pool can hang (every mutant a timeout).
MUTATE_JOBS ?= 1
empty :=
space := $(empty) $(empty)
comma := ,
SANDBOX_DECISIONS := x_sandbox_mode x_weak_sandbox_allowed x_allow_weak_sandbox x_mode_label \
	xǁSandboxLimitsǁ__post_init__ x_fallback_identity x__others_can_reach x_fallback_paths
# The episode core is scoped to its nature/zero-sum path: the natures' observations, rewards
# and infos, the nominal reward of each mode and the perturbed one (the rest of arena.episode
# is the race loop, pinned by the env and parity suites).
EPISODE_NATURE := xǁRaceEpisodeEnvǁ_add_uncertainty xǁRaceEpisodeEnvǁ_rewards \
	xǁRaceEpisodeEnvǁ_reward_key xǁRaceEpisodeEnvǁ_perturbed
# One mutmut run per word; a word is a comma-separated list of mutant-name globs.
MUTATE ?= tracks.laps.* arena.rewards.* leaderboard.ratings.* submissions.protocol.* \
	leaderboard.queue.* leaderboard.results.* agents.selfplay.* arena.uncertainty.* \
	submissions.bundle.* agents.checkpoint.* agents.batch_rarl.* \
	$(subst $(space),$(comma),$(strip $(foreach f,$(SANDBOX_DECISIONS),submissions.sandbox.$(f)*))) \
	$(subst $(space),$(comma),$(strip $(foreach f,$(EPISODE_NATURE),arena.episode.$(f)*)))

mutate: install
	mkdir -p $(ARTIFACTS)
	set -f; for run in $(MUTATE); do \
	  echo "mutmut run $${run//,/ }"; \
	  OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 \
	  $(VENV)/bin/mutmut run --max-children $(MUTATE_JOBS) $${run//,/ } >> $(ARTIFACTS)/mutmut.log 2>&1 \
	    || { echo "mutmut failed on $$run: see $(ARTIFACTS)/mutmut.log"; exit 1; }; \
	done
	$(PY) bench/mutation_report.py --out $(ARTIFACTS)/mutation.json

clean:
	rm -rf $(VENV) $(ARTIFACTS) mutants .pytest_cache .mypy_cache .ruff_cache
