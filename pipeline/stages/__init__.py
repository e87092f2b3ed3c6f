"""The pipeline's stages, one module per ``bcsdf`` command, in data-flow order:
``fiber`` -> ``bake`` -> ``train`` -> ``export`` -> ``render`` -> ``stability`` -> ``report``,
and ``sweep`` (a family of bakes). Each has ``run(cfg, out_root)``; ``dvc.yaml`` wires them."""
