"""Write a trained run's weights as shipped pretrained weights (``linereg/weights/<name>.pt``).

    python scripts/export_pretrained.py outputs/recipe/airplane/rpm_ours_s0 --name rpm_ours_airplane

The file holds the checkpoint the run evaluated (``<run>/metrics.json``), reduced to the model
weights, the run's resolved config without its folders (``paths``) and with portable data paths
(:func:`linereg.pretrained.portable_config`), the cube it was trained in and its epoch: no optimiser, RNG or generator
state. The script then scores the written file on the run's test pairs, as
``linereg-evaluate checkpoint=<name>`` does, and prints that Err_R beside the run's own, for the
entry of :data:`linereg.pretrained.REGISTRY`.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from linereg.checkpoint import load_checkpoint
from linereg.paths import shared_data_dir
from linereg.pretrained import WEIGHTS_DIR, portable_config
from linereg.registration.learned import upgrade_checkpoint
from linereg.train.checkpoint import save_checkpoint

# Config entries that describe the machine and folders of the training run, not the network.
RUN_DEPENDENT = ("paths", "hydra")


def export(run: Path, name: str, out_dir: Path = WEIGHTS_DIR) -> Path:
    """Write ``<out_dir>/<name>.pt`` from the checkpoint ``run`` evaluated; returns the file."""
    state = upgrade_checkpoint(load_checkpoint(run))
    shared = shared_data_dir()
    if shared is None:
        raise SystemExit("export_pretrained.py: error: the shared data folder is absent (set LINEREG_SHARED_DATA)")
    cache = Path(state["config"].get("paths", {}).get("cache_dir") or "data_cache")
    config = {key: value for key, value in state["config"].items() if key not in RUN_DEPENDENT}
    slim = {
        "config": portable_config(config, shared, cache),
        "half_extent": state["half_extent"],
        "model": {key: value.detach().cpu().contiguous() for key, value in state["model"].items()},
        "progress": {"epoch": state["progress"]["epoch"]},
        "pretrained": name,
    }
    return save_checkpoint(slim, out_dir / f"{name}.pt")


def score(checkpoint: Path | str, output_dir: Path) -> float:
    """Mean test Err_R (degrees) of ``linereg-evaluate checkpoint=<checkpoint>`` (its own test pairs)."""
    command = [sys.executable, "-m", "linereg.train.evaluate", f"checkpoint={checkpoint}", f"output_dir={output_dir}"]
    subprocess.run([*command, "progress=false", "num_figures=0"], check=True, stdout=subprocess.DEVNULL)
    return float(json.loads((output_dir / "metrics.json").read_text())["model"]["err_r_deg_mean"])


def _recorded_err_r(metrics: dict) -> str:
    """The run's own test Err_R from its ``metrics.json``, formatted."""
    value = (metrics.get("metrics") or {}).get("test/err_r_deg_mean")
    return "?" if value is None else f"{value:.4f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a run folder of linereg-train")
    parser.add_argument("--name", required=True, help="<experiment>_<protocol>, e.g. rpm_ours_airplane")
    parser.add_argument("--out-dir", type=Path, default=WEIGHTS_DIR, help="where the file goes (default: %(default)s)")
    args = parser.parse_args(argv)
    file = export(args.run, args.name, args.out_dir)
    recorded = json.loads((args.run / "metrics.json").read_text())
    with tempfile.TemporaryDirectory() as scratch:
        err_r = score(args.name if file.parent == WEIGHTS_DIR else file, Path(scratch))
    print(f"{args.name}: {file} ({file.stat().st_size / 1e6:.2f} MB)")
    print(f"  test Err_R {err_r:.4f} deg from the file, {_recorded_err_r(recorded)} as the run recorded it")
    return 0


if __name__ == "__main__":
    sys.exit(main())
