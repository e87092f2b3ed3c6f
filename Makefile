# The two commands of the README:
#   make run    set up, then run the whole pipeline on configs/default.yaml
#   make test   set up, then run the default test suite
CONFIG ?= configs/default.yaml

.PHONY: setup run test bench bench-bake bench-neural bench-render bench-closure bench-cluster bench-exit bench-cloth cloth stability clean
setup:
	./scripts/setup.sh

run: setup
	.venv/bin/bcsdf run $(CONFIG)

test: setup
	.venv/bin/python -m pytest -q --durations=15  # the slowest, for keeping the suite near 10 min

bench: setup
	.venv/bin/python -m pipeline.bench.fiber

bench-bake: setup
	.venv/bin/python -m pipeline.bench.bake

bench-neural: run
	.venv/bin/python -m pipeline.bench.neural

bench-render: run
	.venv/bin/python -m pipeline.bench.render $(CONFIG)

bench-closure: run
	.venv/bin/python -m pipeline.bench.closure $(CONFIG)

bench-exit: setup
	.venv/bin/python -m pipeline.bench.exit

cloth: setup
	.venv/bin/bcsdf run configs/glove.yaml

bench-cloth: cloth
	.venv/bin/python -m pipeline.bench.cloth configs/glove.yaml

bench-cluster: setup
	.venv/bin/python -m pipeline.bench.cluster

stability: setup
	.venv/bin/bcsdf stability $(CONFIG)

clean:
	rm -rf artifacts
