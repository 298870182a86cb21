#!/usr/bin/env bash
# Fill deploy/wheels/ (the images' wheelhouse) with Linux wheels for the images' Python 3.11.
#   deploy/dev/fetch-wheels.sh           torch==2.13.0 and its dependencies (pip prefers a +cpu wheel found through
#                                        its configured find-links/indexes; pass --torch-index URL to name one)
#   deploy/dev/fetch-wheels.sh --all     every wheel the chief, worker and qube-sim images install (offline builds)
# Options: --arch x86_64|aarch64 (default: this machine's), --torch-index URL.
set -euo pipefail
cd "$(dirname "$0")/../.."

ALL=0
ARCH=$(uname -m)
TORCH_INDEX=""
while [ $# -gt 0 ]; do
    case "$1" in
        --all) ALL=1 ;;
        --arch) ARCH=$2; shift ;;
        --torch-index) TORCH_INDEX=$2; shift ;;
        -h|--help) sed -n '2,6p' "$0"; exit 0 ;;
        *) echo "unknown option $1" >&2; exit 2 ;;
    esac
    shift
done

PY=${PYTHON:-$(command -v .venv/bin/python || command -v python3)}
TARGET=(--only-binary=:all: --python-version 3.11 --implementation cp --abi cp311 --platform "manylinux_2_28_$ARCH")
DEST=deploy/wheels
mkdir -p "$DEST"

requirements() {
    # The base dependencies plus the named extras, read from pyproject.toml (build requirements too).
    "$PY" - "$@" <<'PYEOF'
import sys, tomllib
meta = tomllib.load(open("pyproject.toml", "rb"))
reqs = list(meta["build-system"]["requires"]) + list(meta["project"]["dependencies"])
for extra in sys.argv[1:]:
    reqs += meta["project"]["optional-dependencies"][extra]
print("\n".join(reqs))
PYEOF
}

extra_index=()
[ -n "$TORCH_INDEX" ] && extra_index=(--extra-index-url "$TORCH_INDEX")

if [ "$ALL" = 1 ]; then
    mapfile -t reqs < <(requirements learn)
else
    reqs=("torch==2.13.0")
fi
nice "$PY" -m pip download --quiet -c constraints.txt -d "$DEST" "${TARGET[@]}" "${extra_index[@]}" "${reqs[@]}"
ls "$DEST" | grep -i '^torch-' || { echo "no torch wheel was downloaded" >&2; exit 1; }
du -sh "$DEST"
