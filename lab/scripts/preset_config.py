"""Presets as the tools rewrite them: read with every path made absolute, written back as TOML.

A tool that runs a preset with a key changed writes a new config somewhere else, so the paths a
preset gives relative to its own folder (cache, out dir, cohort, DICOM root) are resolved first.
Only the standard library is needed.
"""
import json
import os
import tomllib


def load_absolute(preset):
    """The config at `preset`, its cache_dir, out_dir, cohort and root made absolute (relative
    paths are the preset's folder's, as `aret-pipe run` reads them; the cache and out dir get
    their defaults, "cache" and "out", when the preset leaves them out)."""
    with open(preset, "rb") as f:
        cfg = tomllib.load(f)
    here = os.path.dirname(os.path.abspath(preset))
    absolute = lambda p: os.path.normpath(os.path.join(here, p))
    pipeline, dataset = cfg.setdefault("pipeline", {}), cfg.setdefault("dataset", {})
    pipeline["cache_dir"] = absolute(pipeline.get("cache_dir", "cache"))
    pipeline["out_dir"] = absolute(pipeline.get("out_dir", "out"))
    for key in ("cohort", "root"):
        if key in dataset:
            dataset[key] = absolute(dataset[key])
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
    """A configuration as TOML: top-level tables of scalars and lists, nested tables under them."""
    out = []
    for name, table in tables.items():
        full = f"{prefix}{name}"
        out.append(f"[{full}]")
        out += [f"{k} = {toml_value(v)}" for k, v in table.items() if not isinstance(v, dict)]
        out.append("")
        nested = {k: v for k, v in table.items() if isinstance(v, dict)}
        if nested:
            out.append(toml_text(nested, prefix=f"{full}."))
    return "\n".join(out)
