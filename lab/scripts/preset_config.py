"""Configurations as the lab scripts read and write them. Only the standard library is needed.

A configuration may say `extends = "other.toml"` (relative to its own folder) and hold only its
difference; `aret-pipe` layers it over the file it extends (stages/config/layers.rs).
`load_absolute` reads a configuration the same way, every path made absolute, so a script can
ask what it runs (its out dir, its phantom). A script that runs a configuration with keys
changed writes a small one that `extends` it (`toml_text`), or passes `--set`; it never copies
a preset's tables.
"""
import json
import os
import tomllib

EXTENDS = "extends"
# Keys holding paths, relative to the folder of the file that gives them.
PATH_KEYS = (("pipeline", "cache_dir"), ("pipeline", "out_dir"), ("dataset", "root"), ("dataset", "cohort"))
# The keys that pick a variant of their table, and what each variant reads of that table (its
# sub-tables and keys): a layer that picks a variant drops, from the layers below it, what only
# other variants read, as `aret-pipe` does (stages/config/layers.rs, VARIANTS).
VARIANTS = (
    ("train", "model", {"dense_tv": ("dense_tv",), "vm": ("vm",), "truth": ()}),
    ("select", "localize", {"none": (), "origin": (), "blob": ("blob",)}),
    ("select", "sizing", {"candidates": (), "half_max": ("half_max",), "shadows": ("half_max",)}),
    # roi_center is a word or a position in mm (a list): a position reads nothing either.
    ("drr", "roi_center", {"nodule": (), "lungs": (), "tiles": ("tiles",)}),
    ("dataset", "kind", {"phantom": ("phantom", "cohort"), "dicom": ("root",), "lidc": ("root",)}),
)


def layers(path):
    """[(file, table)] of the configuration at `path` and every file it extends, the lowest
    first; each table without its `extends` key."""
    chain, seen, next_path = [], [], os.path.abspath(path)
    while next_path:
        real = os.path.realpath(next_path)
        if real in seen:
            raise ValueError(f"{next_path}: `extends` comes back to this file")
        seen.append(real)
        with open(next_path, "rb") as f:
            table = tomllib.load(f)
        parent = table.pop(EXTENDS, None)
        chain.append((next_path, table))
        next_path = os.path.join(os.path.dirname(next_path), parent) if parent else None
    return chain[::-1]


def merge(base, top):
    """`top` over `base` (in place): tables merge key by key, other values replace; where `top`
    picks a variant, what only the other variants read goes from `base` first."""
    for table, selector, reads in VARIANTS:
        picked = top.get(table, {}).get(selector) if isinstance(top.get(table), dict) else None
        below = base.get(table)
        if picked is None or not isinstance(below, dict):
            continue
        kept = () if isinstance(picked, list) else reads.get(picked, ())
        for member in {m for members in reads.values() for m in members} - set(kept):
            below.pop(member, None)
    _merge_tables(base, top)
    return base


def _merge_tables(base, top):
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            _merge_tables(base[key], value)
        else:
            base[key] = json.loads(json.dumps(value)) if isinstance(value, (dict, list)) else value


def load_absolute(preset):
    """The configuration at `preset` as `aret-pipe run` layers it (each file it extends first),
    its cache_dir, out_dir, cohort and root made absolute (relative paths are those of the file
    that gives them; the cache and out dir get their defaults, "cache" and "out" beside
    `preset`, when no layer gives them). Keys no layer gives keep their built-in defaults,
    which this does not fill in."""
    cfg = {}
    for path, table in layers(preset):
        here = os.path.dirname(path)
        for section, key in PATH_KEYS:
            value = table.get(section, {}).get(key) if isinstance(table.get(section), dict) else None
            if isinstance(value, str):
                table[section][key] = os.path.normpath(os.path.join(here, value))
        merge(cfg, table)
    here = os.path.dirname(os.path.abspath(preset))
    pipeline = cfg.setdefault("pipeline", {})
    cfg.setdefault("dataset", {})
    pipeline.setdefault("cache_dir", os.path.join(here, "cache"))
    pipeline.setdefault("out_dir", os.path.join(here, "out"))
    return cfg


def toml_value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML for {v!r}")


def toml_text(tables, prefix=""):
    """A configuration as TOML: its top-level keys (`extends`) first, then its tables of
    scalars and lists, nested tables under them."""
    out = []
    if not prefix:
        top = [f"{k} = {toml_value(v)}" for k, v in tables.items() if not isinstance(v, dict)]
        if top:
            out += top + [""]
        tables = {k: v for k, v in tables.items() if isinstance(v, dict)}
    for name, table in tables.items():
        full = f"{prefix}{name}"
        out.append(f"[{full}]")
        out += [f"{k} = {toml_value(v)}" for k, v in table.items() if not isinstance(v, dict)]
        out.append("")
        nested = {k: v for k, v in table.items() if isinstance(v, dict)}
        if nested:
            out.append(toml_text(nested, prefix=f"{full}."))
    return "\n".join(out)
