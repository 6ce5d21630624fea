"""Use the installed wheel from a folder outside the repository (run by .ci/wheel_smoke.sh).

Usage: python wheel_smoke.py <the wheel file>
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import json
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
from packaging.requirements import Requirement

HERE = Path.cwd()
FOREIGN_NAMES = ("losses", "models", "datasets", "train", "registration", "configs")
COMMANDS = ("linereg-train", "linereg-evaluate", "linereg-register", "linereg-benchmark")


def check(condition: bool, message: str) -> None:
    if not condition:
        raise SystemExit(f"wheel smoke test FAILED: {message}")


def run(*command: str, code: int = 0) -> subprocess.CompletedProcess:
    start = time.perf_counter()
    done = subprocess.run(command, cwd=HERE, capture_output=True, text=True, check=False, timeout=600)
    output = done.stdout[-3000:] + done.stderr[-3000:]
    check(done.returncode == code, f"{' '.join(command)} exited {done.returncode}, not {code}:\n{output}")
    print(f"{command[0]}: {time.perf_counter() - start:.1f} s")
    return done


def main(wheel: str) -> None:
    # The wheel installs one top-level name and declares dependencies that this environment satisfies.
    top_level = {name.split("/")[0] for name in zipfile.ZipFile(wheel).namelist()}
    check(top_level == {"linereg", "linereg-0.1.0.dist-info"}, f"the wheel installs {sorted(top_level)}")
    for line in importlib.metadata.requires("linereg") or []:
        requirement = Requirement(line)
        if requirement.marker is not None and not requirement.marker.evaluate({"extra": ""}):
            continue  # an extra, or another platform's variant
        try:
            version = importlib.metadata.version(requirement.name)
        except importlib.metadata.PackageNotFoundError:
            check(False, f"declared dependency {requirement} is not installed")
        check(requirement.specifier.contains(version, prereleases=True), f"{requirement} but {version} is installed")

    import linereg

    site = Path(linereg.__file__).resolve().parent
    check("torch" not in sys.modules, "import linereg loaded torch")
    check(site.parent.name == "site-packages" and (site / "losses").is_dir(), f"linereg comes from {site}")

    import torch

    import linereg.datasets
    import linereg.losses
    import linereg.models
    from linereg.losses.line_intersection import LineMetricOptions, line_intersection_metric

    for module in (linereg.losses, linereg.models, linereg.datasets):
        check(Path(module.__file__).resolve().is_relative_to(site), f"{module.__name__} from {module.__file__}")
    for name in FOREIGN_NAMES:
        spec = importlib.util.find_spec(name)
        check(spec is None or site not in Path(spec.origin or "/").resolve().parents, f"top-level {name} is ours")

    generator = torch.Generator().manual_seed(0)
    src = torch.rand(2, 256, 3, generator=generator, requires_grad=True)
    tgt = torch.rand(2, 256, 3, generator=generator)
    loss = line_intersection_metric(src, tgt, options=LineMetricOptions(num_lines=2000)).value.mean()
    loss.backward()
    check(bool(torch.isfinite(loss)) and src.grad is not None, "the line loss")
    check(sorted(linereg.models.MODELS.names()) == ["dcp_v1", "dcp_v2", "fmr", "rpmnet"], "the model registry")

    from linereg.datasets.procedural import procedural_shape

    cloud = procedural_shape(np.random.default_rng(3)).sample(500, seed=3)  # an asymmetric shape
    shift = cloud + np.array([0.05, 0.0, 0.0])
    result = linereg.register(cloud, shift, num_points=256)
    check(abs(result.transformation[0, 3] - 0.05) < 1e-3 and result.fitness > 0.9, f"register: {result}")

    for command in COMMANDS:  # the help templates are installed with the configs
        usage = run(command, "--help").stdout
        check(f"usage: {command}" in usage, f"{command} --help prints no usage line:\n{usage[:1000]}")
    refused = run("linereg-register", code=2).stderr.strip()
    check(len(refused.splitlines()) == 1 and "source=" in refused, f"linereg-register without a source:\n{refused}")

    from linereg.io import write_point_cloud

    write_point_cloud(HERE / "a.ply", cloud.astype("float32"))
    write_point_cloud(HERE / "b.ply", shift.astype("float32"))
    run("linereg-register", "source=a.ply", "target=b.ply", "num_points=256", "progress=false")
    results = list(HERE.glob("outputs/register/*/result.json"))
    check(len(results) == 1, "linereg-register wrote no result.json")
    check(abs(json.loads(results[0].read_text())["transform"][0][3] - 0.05) < 1e-3, "linereg-register's transform")

    tiny = ("debug=tiny", f"paths.output_dir={HERE / 'run'}", "model.num_neighbors=8", "loss.num_lines=300")
    run("linereg-train", *tiny)
    check((HERE / "run" / "checkpoints" / "last.pt").is_file(), "linereg-train wrote no checkpoint")
    run("linereg-evaluate", f"checkpoint={HERE / 'run'}", f"output_dir={HERE / 'evaluation'}", "progress=false")
    check((HERE / "evaluation" / "metrics.json").is_file(), "linereg-evaluate wrote no metrics.json")

    # Pretrained weights ship inside the wheel and work by name.
    from linereg import pretrained

    shipped = {f"rpm_{loss}_{protocol}" for loss in ("gt", "cd", "ours") for protocol in ("airplane", "human", "real")}
    check(shipped <= set(pretrained.names()), f"pretrained names: {pretrained.names()}")
    check(all(pretrained.path(name).is_relative_to(site) for name in shipped), "pretrained files outside the wheel")
    by_name = ("checkpoint=rpm_ours_airplane", "dataset=procedural", f"output_dir={HERE / 'by_name'}", "progress=false")
    run("linereg-evaluate", *by_name, "trainer.num_points=128", "max_batches=1")
    check((HERE / "by_name" / "metrics.json").is_file(), "linereg-evaluate checkpoint=<name> wrote no metrics.json")

    # Two gloo processes under torchrun, from this folder outside the checkout.
    ddp = (*tiny[:1], f"paths.output_dir={HERE / 'ddp'}", *tiny[2:], "trainer.device=cpu")
    torchrun = (sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2")
    run(*torchrun, "-m", "linereg.train", *ddp)
    check((HERE / "ddp" / "checkpoints" / "last.pt").is_file(), "torchrun: no checkpoint")
    print(
        f"wheel smoke test: linereg {linereg.__version__} from {site}: imports, loss, register, commands, help, "
        "pretrained weights, torchrun OK"
    )


if __name__ == "__main__":
    main(sys.argv[1])
