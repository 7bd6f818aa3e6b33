# Shared by scripts/demo and scripts/test: make .venv (once) and install edgepose into it.
# EDGEPOSE_EXTRAS adds optional extras (e.g. "train" for torch); PYTHON picks the interpreter.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PY=${PYTHON:-python3}
if ! "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
    echo "edgepose needs Python 3.11 or newer; found: $("$PY" --version 2>&1). Set PYTHON=/path/to/python3.11." >&2
    exit 1
fi
if [ ! -x .venv/bin/python ]; then
    echo "setting up .venv ..." >&2
    "$PY" -m venv .venv
fi
extras="${1:-}${EDGEPOSE_EXTRAS:+,$EDGEPOSE_EXTRAS}"
extras="${extras#,}"
.venv/bin/python -m pip install -q -e ".${extras:+[$extras]}"
