# The two commands of the README:
#   make run    set up, then run the whole pipeline on configs/default.yaml
#   make test   set up, then run the default test suite
CONFIG ?= configs/default.yaml

.PHONY: setup run test bench bench-bake bench-neural bench-render bench-closure bench-cluster bench-exit stability clean
setup:
	./scripts/setup.sh

run: setup
	.venv/bin/bcsdf run $(CONFIG)

test: setup
	.venv/bin/python -m pytest -q --durations=15  # the slowest, for keeping the suite near 10 min

bench: setup
	.venv/bin/python -m pipeline.bench_fiber

bench-bake: setup
	.venv/bin/python -m pipeline.bench_bake

bench-neural: run
	.venv/bin/python -m pipeline.bench_neural

bench-render: run
	.venv/bin/python -m pipeline.bench_render $(CONFIG)

bench-closure: run
	.venv/bin/python -m pipeline.bench_closure $(CONFIG)

bench-exit: setup
	.venv/bin/python -m pipeline.bench_exit

bench-cluster: setup
	.venv/bin/python -m pipeline.bench_cluster

stability: setup
	.venv/bin/bcsdf stability $(CONFIG)

clean:
	rm -rf artifacts
