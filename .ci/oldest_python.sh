#!/usr/bin/env bash
# The oldest Python that pyproject.toml claims (3.10): install mcl3d there and import every
# module, so a newer-only feature (e.g. tomllib) cannot land unseen. Skips with a reason when
# no such interpreter is on the machine.
set -euo pipefail
cd "$(dirname "$0")/.."
oldest=$(sed -n 's/^requires-python = ">=\([0-9.]*\),.*/\1/p' pyproject.toml)
python=""
for candidate in "${PYTHON_OLDEST:-}" "python$oldest" /root/.pyenv/versions/"$oldest".*/bin/python"$oldest"; do
  if [ -n "$candidate" ] && "$candidate" -c 'import venv' 2>/dev/null; then python=$candidate; break; fi
done
if [ -z "$python" ]; then
  echo "[ci] no Python $oldest on this machine: import check on the oldest claimed version skipped"
  exit 0
fi
scratch=$(mktemp -d)
venv=$scratch/venv
# what pip leaves in the tree when it builds the wheel, and the venv (1.7 GB a run)
trap "rm -rf '$PWD/build' '$scratch'" EXIT
"$python" -m venv "$venv"
"$venv/bin/python" -m pip install -q --upgrade pip
"$venv/bin/python" -m pip install -q .
cd "$venv"  # import the installed package, not the source tree
"$venv/bin/python" - <<'PY'
import importlib, pkgutil, sys, tempfile, pathlib
import mcl3d
names = [m.name for m in pkgutil.walk_packages(mcl3d.__path__, "mcl3d.")
         if not m.name.endswith("__main__")]  # that one runs the CLI
for name in names:
    importlib.import_module(name)
from mcl3d.core import config

class Probe(config.Section):
    seed: int = 0

toml = pathlib.Path(tempfile.mkdtemp()) / "c.toml"
toml.write_text("seed = 3\n")
assert config.load(Probe, toml).seed == 3
print(f"[ci] Python {sys.version.split()[0]}: imported {len(names)} mcl3d modules, read a TOML config")
PY
