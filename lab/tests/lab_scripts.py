"""What the lab's tests share: the repository, the binary under test, and a study script loaded
as a module (the scripts import their shared helpers, preset_config and metaimage, from their
own folder)."""
import importlib.util
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS = ROOT / "lab" / "scripts"
sys.path.insert(0, str(SCRIPTS))
BIN = os.environ.get("ARET_PIPE_BIN", str(ROOT / "target" / "debug" / "aret-pipe"))


def load(name):
    """lab/scripts/NAME.py as a module."""
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
