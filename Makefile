# The two commands of the README:
#   make run    set up, then run the whole pipeline on configs/default.yaml
#   make test   set up, then run the default test suite
CONFIG ?= configs/default.yaml
# the default config with three model sizes at the full schedule, for error against run time
SIZES = --set name=default_sizes --set 'train.models={small: [32, 32], medium: [64, 64, 64], large: [128, 128, 128]}' \
        --set train.epochs=500 --set render.model=small


.PHONY: setup setup-run run run-sizes test test-slow bench bench-bake bench-neural bench-train bench-encoding bench-render bench-closure bench-cluster bench-exit bench-hair bench-dye bench-near bench-packing bench-sun bench-twisted figures bench-highlight bench-cloth cloth stability clean
setup:
	./scripts/setup.sh

# the main job needs no test tools (pytest, Chromium for the report test); DVC it
# installs, so that `bcsdf run` records its lock and the README's dvc commands work
setup-run:
	BCSDF_EXTRAS=train,onnx,render,stability,dvc ./scripts/setup.sh

run: setup-run
	.venv/bin/bcsdf run $(CONFIG)

# the default ply with the three model sizes (artifacts/default_sizes/): what the neural
# and render benches compare
run-sizes: setup-run
	.venv/bin/bcsdf run configs/default.yaml $(SIZES)

test: setup
	.venv/bin/python -m pytest -q -n 2 --dist loadfile --durations=15  # two workers, a test file each; the slowest printed

test-slow: setup
	.venv/bin/python -m pytest -q -m slow tests  # the long checks: CI runs them after make test

bench: setup
	.venv/bin/python -m pipeline.bench.fiber

bench-bake: setup
	.venv/bin/python -m pipeline.bench.bake

bench-neural: run-sizes
	.venv/bin/python -m pipeline.bench.neural $(SIZES)

bench-train: run-sizes
	.venv/bin/python -m pipeline.bench.train --config configs/default.yaml $(SIZES)

# the plain MLP against feature lines (models/lines.py) on the default table, and against an
# independent bake (another seed, 8x the paths) as the truth; AVX2 kernels as on most users' machines
REF = --set name=default_ref --set bake.seed=7 --set bake.paths_per_phi_i=16000000
bench-encoding: run
	.venv/bin/bcsdf fiber configs/default.yaml $(REF)
	.venv/bin/bcsdf bake configs/default.yaml $(REF)
	ATEN_CPU_CAPABILITY=avx2 .venv/bin/python -m pipeline.bench.encoding --config configs/default.yaml --reference default_ref

bench-render: run-sizes
	.venv/bin/python -m pipeline.bench.render configs/default.yaml $(SIZES)

bench-closure: run
	.venv/bin/python -m pipeline.bench.closure $(CONFIG)

bench-exit: setup
	.venv/bin/python -m pipeline.bench.exit

bench-hair: setup
	.venv/bin/python -m pipeline.bench.hair

bench-dye: setup
	.venv/bin/python -m pipeline.bench.dye

bench-near: setup
	.venv/bin/python -m pipeline.bench.near

bench-packing: setup
	.venv/bin/python -m pipeline.bench.packing

bench-sun: setup
	.venv/bin/python -m pipeline.bench.sun

# the README's headline figures from the default run, then every document's results blocks
figures: run
	.venv/bin/python -m pipeline.bench.headline
	.venv/bin/python -m pipeline.figures

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
