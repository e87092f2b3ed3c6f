"""Loading a config: YAML read strictly (no duplicate keys, no aliases), ``--set`` overrides,
file names resolved against the config's folder, the schema (:mod:`pipeline.config`)
validated, and the members of a ``sweep:`` expanded. Also what only this machine can say:
whether the variants a config names run here.
"""

from __future__ import annotations

import itertools
import json
import shlex
from pathlib import Path

import yaml
from pydantic import ValidationError

from .config import Config, ConfigError


def check_variants(cfg) -> None:
    """Every Mitsuba variant the config names can run on this machine (a ``cuda_*`` one
    needs an NVIDIA GPU and its driver): a :class:`ConfigError` naming the key otherwise.
    Machine-dependent, so called by ``bcsdf`` before any work, not by the validation."""
    keys = {"bake.variant": cfg.bake.variant}
    if cfg.bundle is not None:
        keys["render.variant"] = cfg.render.variant
    if cfg.cloth is not None:
        keys["cloth.variant"] = cfg.cloth.variant
    wanted = {k: v for k, v in keys.items() if v.startswith("cuda")}
    if not wanted:
        return
    import drjit as dr

    if not dr.has_backend(dr.JitBackend.CUDA):
        k, v = next(iter(wanted.items()))
        raise ConfigError(f"{k}: {v} needs an NVIDIA GPU and its CUDA driver, and this machine has none; "
                          f"use {v.replace('cuda', 'llvm')}")


def _format_errors(err: ValidationError) -> str:
    lines, seen = [], set()
    for e in err.errors():
        # a union's branches ('float', 'list[tuple[float, float]]') are not keys: name the key once
        key = ".".join(str(p) for p in e["loc"] if not str(p).startswith(("function-", "tagged-union"))
                       and "[" not in str(p) and str(p) not in ("float", "int", "str", "bool"))
        if key in seen:
            continue
        seen.add(key)
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            msg = "unknown key (check the spelling; see configs/default.yaml for the keys)"
        elif e["type"] == "missing":
            msg = "required key is missing"
        elif "input" in e and not isinstance(e["input"], (dict, list)) and "(got " not in msg:
            msg += f" (got {e['input']!r})"  # unless the check already said what it got
        lines.append(f"  {key or '<top level>'}: {msg}")
    return "\n".join(lines)


def apply_overrides(data: dict, overrides) -> dict:
    """``data`` with ``KEY=VALUE`` overrides applied (``bake.paths_per_phi_i=20000``).

    ``KEY`` is a dotted path into the config; ``VALUE`` is read as YAML, so numbers,
    lists (``train.models={s: [8]}``) and ``null`` work. Missing sections are created;
    the result is validated like any config, so a misspelt key is named as unknown.
    """
    data = json.loads(json.dumps(data))  # a deep copy
    for item in overrides or ():
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {item!r}: write KEY=VALUE, e.g. --set bake.paths_per_phi_i=20000")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise ConfigError(f"--set {item!r}: the value is not valid YAML ({e})") from None
        try:
            set_key(data, key.strip(), value)
        except ConfigError as e:
            raise ConfigError(f"--set {item!r}: {e}") from None
    return data


def set_key(data: dict, key: str, value) -> None:
    """``data[a][b][c] = value`` for ``key = "a.b.c"``, creating missing sections."""
    node, parts = data, key.split(".")
    for i, part in enumerate(parts[:-1]):
        if node.get(part) is None:
            node[part] = {}
        if not isinstance(node[part], dict):
            raise ConfigError(f"{'.'.join(parts[:i + 1])} is a value, not a section")
        node = node[part]
    node[parts[-1]] = value


def sweep_axes(cfg: Config) -> dict[str, list]:
    """``cfg``'s sweep axes, the seed axis extended by ``family.held_out_seeds`` (the draws
    baked at held-out packings only): every value some member takes, in member order."""
    axes = {k: list(v) for k, v in (cfg.sweep or {}).items()}
    if cfg.family is not None and cfg.family.held_out_seeds:
        axes["bundle.seed"] += cfg.family.held_out_seeds
    return axes


def sweep_members(cfg: Config) -> list[tuple[dict, Config]]:
    """The members of ``cfg``'s sweep: every combination of its axes' values (a grid, the
    first axis slowest), then each held-out packing at each of ``family.held_out_seeds``;
    each ``({key: value}, Config)``, named after its values (``packing-0.3_seed-2``) and
    validated like any config.

    Raises :class:`ConfigError` naming the member and the key of the first invalid one.
    """
    if not cfg.sweep:
        return []
    axes = sweep_axes(cfg)
    grid = [dict(zip(axes, picks)) for picks in itertools.product(*(range(len(v)) for v in cfg.sweep.values()))]
    f = cfg.family
    extra = [] if f is None else [
        {k: {"bundle.packing": i, "bundle.seed": len(cfg.sweep["bundle.seed"]) + j}[k] for k in axes}
        for i, p in enumerate(axes["bundle.packing"]) if f.holds_out(p) for j in range(len(f.held_out_seeds))]
    short = {k: k.rsplit(".", 1)[-1] for k in axes}
    if len(set(short.values())) < len(short):  # bundle.seed and bake.seed: keep the whole key
        short = {k: k for k in axes}
    base = cfg.model_dump(mode="json", exclude={"sweep", "family"})  # a member is one ply
    labels = {k: _labels(values) for k, values in axes.items()}
    members = []
    for n, picks in enumerate(grid + extra):
        point = {k: axes[k][i] for k, i in picks.items()}
        name = "_".join(f"{short[k]}-{labels[k][i]}" for k, i in picks.items())
        if len(name) > 100:
            name = f"member-{n:03d}"
        data = json.loads(json.dumps(base))
        data["name"] = name
        try:
            for key, value in point.items():
                set_key(data, key, value)
            member = Config.model_validate(data)
        except (ConfigError, ValidationError) as e:
            what = _format_errors(e) if isinstance(e, ValidationError) else f"  {e}"
            raise ConfigError(f"sweep member {name} ({', '.join(f'{k}={v!r}' for k, v in point.items())}) "
                              f"is not a valid config:\n{what}") from None
        members.append((point, member))
    return members


def _labels(values) -> list[str]:
    """Each value of an axis as it reads in a member's folder name: its short form, or its
    index where it has none or where another value of the axis prints alike (0.1 and
    0.1000001 would otherwise share one member folder)."""
    def text(v):
        t = f"{v:g}" if isinstance(v, float) else str(v)
        ok = not isinstance(v, (dict, list)) and t and all(c.isalnum() or c in "_.-" for c in t)
        return t if ok else None
    texts = [text(v) for v in values]
    return [t if t is not None and texts.count(t) == 1 else f"v{k}" for k, t in enumerate(texts)]


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader for configs: refuses a key given twice in one mapping (the last
    would win), a key that is not a plain name or number, and aliases (``*name``: a config
    needs none, and nested aliases expand a 1 kB file to 10^9 values)."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.events.AliasEvent):
            mark = self.peek_event().start_mark
            raise ConfigError(f"line {mark.line + 1}: YAML aliases (*name) are not accepted in a config; "
                              "write the value out where it is used")
        return super().compose_node(parent, index)

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                raise ConfigError(f"line {key_node.start_mark.line + 1}: a key must be a plain name or number, "
                                  "not a list or mapping")
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise ConfigError(f"line {key_node.start_mark.line + 1}: the key {key!r} is given twice; "
                                  "keep one of them")
            seen.add(key)
        return super().construct_mapping(node, deep)


def load_config(path, overrides=()) -> Config:
    """Read and validate a YAML config; raise :class:`ConfigError` naming every bad key.

    ``overrides``: ``KEY=VALUE`` strings applied before validation (:func:`apply_overrides`).
    """
    path = Path(path)
    try:
        data = yaml.load(path.read_text(), Loader=_UniqueKeyLoader)
    except FileNotFoundError:
        raise ConfigError(f"config file {path} does not exist") from None
    except IsADirectoryError:
        raise ConfigError(f"{path} is a folder; give a YAML file, e.g. configs/default.yaml") from None
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start}); save the config as UTF-8") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot be read ({e.strerror})") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({e})") from None
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None
    except RecursionError:
        raise ConfigError(f"{path}: nested too deeply to be a config (lists or mappings inside each other "
                          "hundreds of levels down)") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of keys at the top level")
    data = apply_overrides(data, overrides)
    where = f"{path} with --set {' '.join(overrides)}" if overrides else str(path)
    if "name" in data and data["name"] is None:  # `name:` left empty, or --set name=null
        raise ConfigError(f"{where}: name is empty; give the artifacts folder a name (letters, digits, _ . -), "
                          f"or leave the key out to use the file's ({path.stem!r})")
    data.setdefault("name", path.stem)
    _resolve_paths(data, path.parent)
    try:
        cfg = Config.model_validate(data)
    except ValidationError as e:
        raise ConfigError(f"{where}: invalid config\n{_format_errors(e)}") from None
    cfg._source = " ".join([shlex.quote(str(path))] + [f"--set {shlex.quote(o)}" for o in overrides])
    try:  # a sweep's members are refused here, before anything runs
        configs = [cfg] + [m for _, m in sweep_members(cfg)]
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    for c in configs:
        if c.fiber.table is not None and c.fiber.model == "table" and not Path(c.fiber.table.path).exists():
            who = "" if c is cfg else f"sweep member {c.name}: "
            raise ConfigError(f"{where}: {who}fiber.table.path: {c.fiber.table.path} does not exist")
    return cfg


# file names in a config are relative to the config's folder
PATH_KEYS = ("bundle.file", "fiber.table.path", "cloth.model")


def _resolve_paths(data: dict, base: Path) -> None:
    """Make the config's file names (also those of sweep axes) absolute, in place."""
    def resolve(v):
        return str((base / v).resolve()) if isinstance(v, str) and v else v

    sweep = data.get("sweep")
    for key in PATH_KEYS:
        node, parts = data, key.split(".")
        for part in parts[:-1]:
            node = node.get(part) if isinstance(node, dict) else None
        if isinstance(node, dict) and parts[-1] in node:
            node[parts[-1]] = resolve(node[parts[-1]])
        if isinstance(sweep, dict) and isinstance(sweep.get(key), list):
            sweep[key] = [resolve(v) for v in sweep[key]]
