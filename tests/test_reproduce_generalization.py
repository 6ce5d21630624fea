"""``scripts/reproduce_generalization.sh``: the runs behind the generalization tables are the README's
cell commands with a dataset choice, every fold and seed, and each resolves to a training config."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

from linereg import pretrained

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "scripts" / "reproduce_generalization.sh"
BODIES = {"human_man", "human_neutral", "human_woman"}


def _dry(**env: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        ["bash", str(SCRIPT)], env=dict(os.environ) | {"DRY": "1", **env}, capture_output=True, text=True
    )


def _parts(folder: str) -> tuple[str, str, str, str]:
    """``(step, body or "", cell or settings, seed)`` of a run folder ``out/<step>/[<body>/]<name>_s<seed>``."""
    parts = Path(folder).parts
    name, seed = parts[-1].rsplit("_s", 1)
    return parts[1], parts[2] if len(parts) == 4 else "", name, seed


def test_every_fold_and_seed_of_every_step_is_a_cell_command_with_a_dataset(hydra_compose):
    result = _dry(OUT="out", SEEDS="0 1", CELLS="rpm_cd rpm_ours")
    runs = dict(line.split(" ", 1) for line in result.stdout.splitlines())
    steps = [_parts(folder)[0] for folder in runs]
    assert {step: steps.count(step) for step in set(steps)} == {
        "unseen_body": 3 * 2 * 2,  # bodies x cells x seeds
        "mixed_pairs": 2 * 2,
        "human_choice": 3 * 2,  # three settings of RPM-Ours
        "objects": 2 * 2,  # the general model and its Chamfer twin x seeds
        "objects_and_rooms": 2 * 2,  # the same with the room frames
        "objects_and_rooms_gap20": 2 * 2,  # and with the rooms at the test pairs' gap throughout
        "objects_then_rooms": 2 * 2,  # and with the rooms alone at that gap after it
        "objects_then_far_rooms": 2 * 2,  # or with the rooms at that gap beside the objects after it
        "real_choice": 2 * 2,  # the Real cells without easier pairs first x seeds
        "dcp_choice": 2 * 2,  # DCP's cd and ours on Airplane without the full-range stage x seeds
        "human_stretch": 2 * 2,  # the Human cells on stretched training pairs x seeds
        "recipe": 3 * 2 * 2,  # the protocols x cells x the two seeds besides the shipped one
    }
    for folder, args in runs.items():
        step, body, name, seed = _parts(folder)
        cell = "rpm_ours" if step == "human_choice" else re.sub(r"_(test_gap|stretch0\.2|easy_only)$", "", name)
        if step == "recipe":
            assert args == f"experiment={cell} protocol={body} seed={seed}" and seed in ("1", "2")
        assert args.startswith(f"experiment={cell} ") and args.endswith(f" seed={seed}")
        if body in BODIES:
            assert f"protocol=human dataset=human_unseen_body dataset.held_out={body} " in args
        if step == "mixed_pairs":
            assert "protocol=airplane dataset=airplane_mixed_pairs " in args
        if step == "dcp_choice":
            assert args == f"experiment={cell} protocol=airplane curriculum=cpu_airplane seed={seed}"
        if step == "real_choice":
            assert args == f"experiment={cell} protocol=real curriculum.stages.easy.variant=null seed={seed}"
        if step == "human_stretch":
            assert (
                args
                == f"experiment={cell} protocol=human +dataset.splits.train.protocol.anisotropic_scale=0.2 seed={seed}"
            )
        if step.startswith("objects"):
            data = "objects" if step == "objects" else "objects_and_rooms"
            assert f"protocol=airplane dataset={data} task_name={cell}_objects " in args
            stage = {"objects_then_rooms": "4", "objects_then_far_rooms": "2"}.get(step)
            assert (f"curriculum.stages.full.epochs={stage} " in args) == (stage is not None)
            variant = {"objects_then_rooms": "rooms_only", "objects_then_far_rooms": "far_rooms"}.get(step)
            assert (f"curriculum.stages.full.variant={variant} " in args) == (variant is not None)
            assert ("dataset.datasets.rooms.variants.easy.frame_gap=20 " in args) == step.endswith("_gap20")
        if step == "human_choice":
            nu, lines = name.removeprefix("rpm_ours_nu").split("_lines")
            assert f"loss.nu0={nu} loss.num_lines={lines} " in args
    for args in runs.values():
        cfg = hydra_compose("train", [*args.split(), f"paths.root_dir={ROOT}"])
        assert cfg.dataset.name in ("mesh_folder", "modelnet40", "rgbd_sequence", "concat")


def test_an_unknown_step_is_one_line_and_exit_code_2():
    result = _dry(STEPS="unseen_body leave_two_out")
    assert result.returncode == 2 and result.stdout == ""
    steps = "unseen_body, mixed_pairs, human_choice, objects, rooms, real_choice, dcp_choice, human_stretch, seeds"
    assert result.stderr.strip() == f"reproduce_generalization.sh: error: unknown step 'leave_two_out' ({steps})"


def test_the_scores_find_linked_runs_and_count_where_the_general_model_wins(tmp_path):
    """``score_generalization.py`` follows runs linked into its folder, and its general-model table
    counts, per protocol, the splits that protocol never trained on where the general model's mean
    is at most that protocol's RPM-CD: the shipped network, and the mean over its seeds."""
    from scripts import _generalization_tables as tables
    from scripts import score_generalization as scores

    elsewhere = tmp_path / "elsewhere" / "run"
    elsewhere.mkdir(parents=True)
    (elsewhere / "metrics.json").write_text("{}")
    (tmp_path / "runs" / "objects").mkdir(parents=True)
    (tmp_path / "runs" / "objects" / "rpm_ours_s1").symlink_to(elsewhere)
    assert scores.run_folders(tmp_path / "runs", "objects") == {
        "objects/rpm_ours_s1": tmp_path / "runs/objects/rpm_ours_s1"
    }
    (tmp_path / "runs" / "recipe" / "airplane").mkdir(parents=True)
    for cell in ("rpm_cd_s1", "rpm_ours_s1"):
        (tmp_path / "runs" / "recipe" / "airplane" / cell).symlink_to(elsewhere)
    seed_jobs = [job for job in scores.object_jobs(tmp_path / "runs") if job.key.startswith("general/recipe/")]
    assert {job.key.rsplit("/", 1)[1] for job in seed_jobs} == {d for _, _, d in tables.OBJECT_SPLITS} - {
        "airplane_views"
    }  # RPM-CD's other seeds, off its own test pairs only
    assert {job.key.rsplit("/", 2)[1] for job in seed_jobs} == {"rpm_cd_s1"}

    found = {}
    shipped = tables.GENERAL_SHIPPED  # the data the shipped general model was trained on
    assert f" dataset={shipped} " in pretrained.entry(tables.GENERAL).command
    other = next(step for step in tables.GENERAL_DATA if step != shipped)
    for protocol, _, dataset in tables.OBJECT_SPLITS:
        found[f"general/{shipped}/rpm_ours_s1/{dataset}"] = {"model": 2.0, "identity": 40.0}
        found[f"general/{shipped}/rpm_cd_s1/{dataset}"] = {"model": 3.5 if protocol == "real" else 1.5}
        found[f"general/{other}/rpm_ours_s1/{dataset}"] = {"model": 5.0}
        found[f"general/rpm_ours_objects/{dataset}"] = {"model": 4.0, "identity": 40.0}
        for own in tables.SPLITS:  # each protocol's RPM-CD: 1 on its own test pairs, 3 elsewhere
            mine = own == protocol and dataset in tables.PROTOCOL_DATA
            found[f"general/rpm_cd_{own}/{dataset}"] = {"model": 1.0 if mine else 3.0}
            if own == "airplane" and not mine:  # its seed 1 at 2: a mean of 2.5 off its protocol
                found[f"general/recipe/airplane/rpm_cd_s1/{dataset}"] = {"model": 2.0}
    table = tables.objects_table(found)
    data = tables.GENERAL_DATA[shipped]
    assert f"| `rpm_ours_objects` | {data} | 3.00 (4.00, 2.00) |" in table  # the shipped network is seed 0
    assert f"| `rpm_ours_objects` | {tables.GENERAL_DATA[other]} | 5.00 | 5.00 |" in table
    assert "| `rpm_cd_airplane` | its protocol | 1.00* | 2.50 (3.00, 2.00) |" in table
    assert "| `rpm_cd_human` | its protocol | 3.00 | 3.00 |" in table
    assert "| identity (no motion) |  | 40.00 |" in table
    splits = len(tables.OBJECT_SPLITS)
    assert f"- on {data}: `rpm_ours` (mean) <= `rpm_cd` on the same data on 3 of {splits} splits" in table
    outside = splits - 1
    for protocol in tables.SPLITS:  # the mean, 3, ties every shipped RPM-CD off its protocol's test pairs
        name = protocol.capitalize()
        verdict = f"`rpm_cd_{protocol}` on {outside} of {outside} splits {name} never trained on (the shipped network"
        assert f"on {data}: `rpm_ours` (mean) <= {verdict}" in table
        assert f"on {tables.GENERAL_DATA[other]}: `rpm_ours` (mean) <= `rpm_cd_{protocol}` on 0 of {outside}" in table
    assert "Airplane never trained on (the shipped network, seed 0); on 0 against its mean over 2 seeds" in table
    assert "Human never trained on (the shipped network, seed 0)\n" in table


def test_the_seeds_step_trains_any_backbone_at_any_seed_of_the_chosen_protocols():
    result = _dry(OUT="out", STEPS="seeds", CELLS="fmr_cd fmr_ours", PROTOCOL_SEEDS="0 1 2", PROTOCOLS="human real")
    runs = dict(line.split(" ", 1) for line in result.stdout.splitlines())
    assert set(runs) == {
        f"out/recipe/{protocol}/fmr_{loss}_s{seed}"
        for protocol in ("human", "real")
        for loss in ("cd", "ours")
        for seed in "012"
    }
    assert runs["out/recipe/real/fmr_ours_s2"] == "experiment=fmr_ours protocol=real seed=2"


def test_the_protocol_tables_count_where_the_line_loss_holds_per_backbone():
    """Beside each backbone's rows, the splits beyond the protocol's test pairs where its line-loss
    cell is at most its Chamfer cell: on the mean, and on at least 2 of 3 seeds paired by number."""
    from scripts import _generalization_tables as tables

    found = {}
    for protocol, splits in tables.SPLITS.items():
        for _, dataset in splits:
            pairs = dataset or "test"
            # Ours wins seeds 0 and 2 (mean 1.67 against 2) except on the armadillo, where it loses all.
            losses = [(9.0, 2.0)] * 3 if dataset == "human_armadillo" else [(1.0, 2.0), (3.0, 2.0), (1.0, 2.0)]
            for seed, (ours, cd) in enumerate(losses):
                found[f"recipe/{protocol}/fmr_ours_s{seed}/{pairs}"] = {"model": ours}
                found[f"recipe/{protocol}/fmr_cd_s{seed}/{pairs}"] = {"model": cd}
    table = tables.shipped_table(found)
    assert "| `fmr_ours_real` | 1.67 (1.00, 3.00, 1.00) | 1.67 (1.00, 3.00, 1.00) |" in table
    verdict = (
        "- `fmr_ours` <= `fmr_cd` beyond the protocol's test pairs: "
        "on the mean on {} of {} splits, on a majority of 3 seed(s) on {}"
    )
    assert verdict.format(2, 2, 2) in table.split("### human")[0]  # airplane
    assert verdict.format(1, 2, 1) in table.split("### human")[1].split("### real")[0]
    assert verdict.format(2, 2, 2) in table.split("### real")[1]
    assert "rpm_ours` <=" not in table  # no RPM-Net scores, no verdict


def test_each_schedule_choice_sets_the_recipe_beside_its_alternative_on_validation_and_test():
    from scripts import _generalization_tables as tables

    found = {}
    for loss, (recipe, alternative) in {"cd": (2.0, 3.0), "ours": (1.0, 4.0)}.items():
        for split in ("val", "test"):
            found[f"dcp_choice/recipe/dcp_{loss}_s0/{split}"] = {"model": recipe}
            found[f"dcp_choice/easy_only/dcp_{loss}_easy_only_s0/{split}"] = {"model": alternative}
    table = tables.schedule_tables(found)
    assert "### Airplane, DCP's full-range stage" in table and "### Real" not in table
    assert "| schedule | `dcp_cd` validation | `dcp_cd` test | `dcp_ours` validation | `dcp_ours` test |" in table
    assert "| easy, then full (the recipe) | 2.00 | 2.00 | 1.00 | 1.00 |" in table
    assert "| easy | 3.00 | 3.00 | 4.00 | 4.00 |" in table
