#!/usr/bin/env bash
# Build the wheel, install it (not editable) into a throwaway venv and use it from outside the repo.
# Third-party packages come from the project venv (a .pth line; its editable linereg is not on that
# path), so no download is needed; .ci/wheel_smoke.py checks that the wheel's declared dependencies
# are satisfied there.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
start=$SECONDS
rm -rf build  # setuptools reuses build/lib: a stale file there would enter the wheel
"$PY" -m pip wheel --quiet --no-deps --no-build-isolation --wheel-dir "$work/wheel" .
"$PY" -m venv --without-pip "$work/venv"
"$PY" -m pip --python "$work/venv/bin/python" install --quiet --no-deps --no-index "$work"/wheel/linereg-*.whl
project_site=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
smoke_site=$("$work/venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
echo "$project_site" > "$smoke_site/project_dependencies.pth"
mkdir "$work/run"
cp .ci/wheel_smoke.py "$work/run/"
(cd "$work/run" && env -u PYTHONPATH PATH="$work/venv/bin:$PATH" OMP_WAIT_POLICY=PASSIVE \
    "$work/venv/bin/python" wheel_smoke.py "$work"/wheel/linereg-*.whl)
rm -rf build
echo "wheel smoke test passed in $((SECONDS - start)) s"
