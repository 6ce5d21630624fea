"""One import name: every module is ``linereg.<...>``; the top-level folders are never packages of their own."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

import linereg

ROOT = Path(__file__).resolve().parent.parent
SUBPACKAGES = ("losses", "models", "datasets", "registration", "train")
OLD_IMPORT = re.compile(rf"^\s*(from|import)\s+({'|'.join(SUBPACKAGES)})(\.|\s|$)", re.M)
OLD_TARGET = re.compile(rf"_target_:\s*({'|'.join(SUBPACKAGES)})\.")


def _sources(*suffixes: str) -> list[Path]:
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=False).stdout.split()
    if not tracked:  # not a git checkout (e.g. an sdist): every file below the root
        tracked = [str(p.relative_to(ROOT)) for p in ROOT.rglob("*") if ".venv" not in p.parts]
    return [ROOT / name for name in tracked if name.endswith(suffixes) and (ROOT / name).is_file()]


def test_no_module_imports_the_old_top_level_names():
    offenders = [
        f"{path.relative_to(ROOT)}:{text[: match.start()].count(chr(10)) + 1}: {match.group(0).strip()}"
        for path in _sources(".py")
        for text in [path.read_text()]
        for match in OLD_IMPORT.finditer(text)
    ]
    assert not offenders, "import linereg.<package> instead:\n" + "\n".join(offenders)


def test_no_config_targets_the_old_top_level_names():
    offenders = [str(path.relative_to(ROOT)) for path in _sources(".yaml") if OLD_TARGET.search(path.read_text())]
    assert not offenders, f"_target_ must name linereg.<package>...: {offenders}"


def test_importing_every_module_loads_no_top_level_package():
    """Walk every module of the package in a fresh interpreter; none may appear under a second name."""
    script = f"""
import importlib, pkgutil, sys
import linereg
names = []
for package in {[f"linereg.{name}" for name in SUBPACKAGES]!r}:
    module = importlib.import_module(package)
    names += [info.name for info in pkgutil.walk_packages(module.__path__, package + ".")]
names += [info.name for info in pkgutil.iter_modules([linereg.__path__[0]], "linereg.")]
for name in names:
    importlib.import_module(name)
top = sorted(name for name in sys.modules if name.split(".")[0] in {SUBPACKAGES!r})
print(len(names), top)
assert not top, top
"""
    result = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stderr[-3000:] + result.stdout[-3000:]
    assert int(result.stdout.split()[0]) > 40, result.stdout


def test_checkout_subpackages_come_from_this_checkout():
    import linereg.losses

    assert Path(linereg.losses.__file__).resolve().is_relative_to(Path(linereg.__file__).resolve().parent.parent)


def test_import_linereg_does_not_load_torch():
    script = "import sys, linereg; assert 'torch' not in sys.modules; assert callable(linereg.register)"
    result = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stderr[-2000:]


def test_lazy_attribute_error_names_the_attribute():
    try:
        linereg.no_such_thing  # noqa: B018
    except AttributeError as err:
        assert "no_such_thing" in str(err)
    else:
        raise AssertionError("expected AttributeError")


def _declared() -> dict[str, set[str]]:
    """Normalised distribution names of the base dependencies (``""``) and of each extra."""
    from packaging.requirements import Requirement

    tomllib = pytest.importorskip("tomllib")  # Python 3.11+

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    groups = {"": project["dependencies"], **project["optional-dependencies"]}
    return {group: {_normalise(Requirement(line).name) for line in lines} for group, lines in groups.items()}


def _normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


# The extras a layer may use besides the base dependencies (imported inside the functions that need them).
EXTRAS_ALLOWED = {
    "linereg": set(),
    "losses": set(),
    "models": set(),
    "datasets": {"train"},  # h5py: ModelNet40's HDF5 files
    "registration": {"baselines", "plot"},  # fricp_cpp; matplotlib: the alpha-recall plot
    "train": {"train", "cluster"},
}


def test_every_third_party_import_is_declared():
    import ast
    import importlib.metadata

    distributions = importlib.metadata.packages_distributions()
    declared = _declared()
    own = {"linereg", "__future__"}
    missing = []
    for folder, extras in EXTRAS_ALLOWED.items():
        allowed = set().union(declared[""], *(declared[extra] for extra in extras))
        for path in sorted((ROOT / folder).glob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    names = [alias.name for alias in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    top = name.split(".")[0]
                    if top in own or top in sys.stdlib_module_names:
                        continue
                    provided = {_normalise(d) for d in distributions.get(top, [top])}
                    # open3d-cpu provides open3d; either satisfies the platform-dependent requirement
                    if not provided & allowed and not ("open3d" in provided and "open3d-cpu" in allowed):
                        missing.append(f"{path.relative_to(ROOT)}: {name} ({', '.join(sorted(provided))})")
    assert not missing, "undeclared dependencies:\n" + "\n".join(missing)


def test_every_config_folder_is_packaged():
    tomllib = pytest.importorskip("tomllib")
    packages = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = {
        ".".join(("linereg", *path.relative_to(ROOT).parent.parts)) for path in (ROOT / "configs").rglob("*.yaml")
    }
    assert folders - packages == set(), "config folders missing from [tool.setuptools] packages in pyproject.toml"
