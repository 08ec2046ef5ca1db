#!/usr/bin/env bash
# Create .venv and install pomil into it (with test tools when called with "test").
# Torch comes first as a CPU build: on this kind of machine `pip install torch==2.13.0`
# takes the CPU wheel lying on disk; elsewhere set POMIL_TORCH_INDEX to PyTorch's CPU
# index (https://download.pytorch.org/whl/cpu) or preinstall the torch you want.
# pomil itself asks for torch>=2.2, which an installed torch satisfies: nothing more is pulled.
set -euo pipefail
cd "$(dirname "$0")/.."
venv="${POMIL_VENV:-.venv}"
extras="${1:-}"
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
pip=("$venv/bin/python" -m pip --disable-pip-version-check)
if ! "$venv/bin/python" -c "import torch" 2>/dev/null; then
  echo "setup: installing ${POMIL_TORCH:-torch==2.13.0} (CPU)" >&2
  if [ -n "${POMIL_TORCH_INDEX:-}" ]; then
    "${pip[@]}" install -q "${POMIL_TORCH:-torch==2.13.0}" --index-url "$POMIL_TORCH_INDEX"
  else
    "${pip[@]}" install -q "${POMIL_TORCH:-torch==2.13.0}"
  fi
fi
stamp="$venv/.pomil-installed${extras:+-$extras}"
want="$(cat pyproject.toml | sha256sum | cut -c1-16)"
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "setup: installing pomil${extras:+[$extras]} into $venv" >&2
  "${pip[@]}" install -q -e ".${extras:+[$extras]}" 2>&1 | grep -v "^WARNING: Location" >&2 || true
  "$venv/bin/python" -c "import pomil, torch, mujoco, gymnasium" || { echo "setup: install failed" >&2; exit 1; }
  echo "$want" > "$stamp"
fi
