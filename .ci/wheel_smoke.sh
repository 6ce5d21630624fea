#!/usr/bin/env bash
# Build the wheel; check that linereg[train] installs from the package registry without a compiler
# (wheels only, see below; pip reads metadata only where the registry serves it, PEP 658); install the
# wheel (not editable) into a throwaway venv and use it from outside the repo. Third-party packages come
# from the project venv (a .pth line; its editable linereg is not on that path), so that part downloads
# nothing; .ci/wheel_smoke.py checks that the wheel's declared dependencies are satisfied there.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
start=$SECONDS
rm -rf build  # setuptools reuses build/lib: a stale file there would enter the wheel
"$PY" -m pip wheel --quiet --no-deps --no-build-isolation --wheel-dir "$work/wheel" .
wheel=$(echo "$work"/wheel/linereg-*.whl)
# Wheels only, with one exception: hydra-core pins antlr4-python3-runtime 4.9, which the registry has as a
# source archive only. It is pure Python: built here, it must give a py3-none-any wheel.
"$PY" -m pip wheel --quiet --no-deps --no-binary=:all: --wheel-dir "$work/pure" "antlr4-python3-runtime==4.9.*"
for built in "$work"/pure/*.whl; do
    [[ $built == *-py3-none-any.whl ]] || { echo "not pure Python: $built" >&2; exit 1; }
done
"$PY" -m pip install --quiet --dry-run --ignore-installed --only-binary=:all: --find-links "$work/pure" "$wheel[train]" \
    || { echo "a dependency of linereg[train] has no wheel for this Python and platform" >&2; exit 1; }
"$PY" -m venv --without-pip "$work/venv"
"$PY" -m pip --python "$work/venv/bin/python" install --quiet --no-deps --no-index "$wheel"
project_site=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
smoke_site=$("$work/venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
echo "$project_site" > "$smoke_site/project_dependencies.pth"
mkdir "$work/run"
cp .ci/wheel_smoke.py "$work/run/"
(cd "$work/run" && env -u PYTHONPATH PATH="$work/venv/bin:$PATH" OMP_WAIT_POLICY=PASSIVE \
    "$work/venv/bin/python" wheel_smoke.py "$wheel")
rm -rf build
echo "wheel smoke test passed in $((SECONDS - start)) s"
