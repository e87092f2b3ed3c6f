# The two commands of the README:
#   make run    set up, then run the whole pipeline on configs/default.yaml
#   make test   set up, then run the default test suite
CONFIG ?= configs/default.yaml

.PHONY: setup setup-run run test bench bench-bake bench-neural bench-train bench-render bench-closure bench-cluster bench-exit bench-twisted bench-highlight bench-cloth cloth stability clean
setup:
	./scripts/setup.sh

# the main job needs no test tools (pytest, DVC, Chromium for the report test)
setup-run:
	BCSDF_EXTRAS=train,onnx,render,stability ./scripts/setup.sh

run: setup-run
	.venv/bin/bcsdf run $(CONFIG)

test: setup
	.venv/bin/python -m pytest -q -n 2 --dist loadfile --durations=15  # two workers, a test file each; the slowest printed

bench: setup
	.venv/bin/python -m pipeline.bench.fiber

bench-bake: setup
	.venv/bin/python -m pipeline.bench.bake

bench-neural: run
	.venv/bin/python -m pipeline.bench.neural

bench-train: run
	.venv/bin/python -m pipeline.bench.train --config $(CONFIG)

bench-render: run
	.venv/bin/python -m pipeline.bench.render $(CONFIG)

bench-closure: run
	.venv/bin/python -m pipeline.bench.closure $(CONFIG)

bench-exit: setup
	.venv/bin/python -m pipeline.bench.exit

bench-highlight: run
	.venv/bin/python -m pipeline.bench.highlight $(CONFIG)

bench-twisted: setup
	.venv/bin/python -m pipeline.bench.twisted --config $(CONFIG)

cloth: setup-run
	.venv/bin/bcsdf run configs/glove.yaml

bench-cloth: cloth
	.venv/bin/python -m pipeline.bench.cloth configs/glove.yaml

bench-cluster: setup
	.venv/bin/python -m pipeline.bench.cluster

stability: setup-run
	.venv/bin/bcsdf stability $(CONFIG)

clean:
	rm -rf artifacts
