"""scripts/reproduce_report.py: tables beside the paper's numbers, seeds, curves, figures."""

from __future__ import annotations

import json

from scripts import reproduce_report

KEYS = ("err_r_deg", "err_t_l1", "err_t_l2", "err_pw_l1", "err_pw_l2")


def _run(folder, err_r: float, seconds: float) -> None:
    folder.mkdir(parents=True)
    metrics = {f"test/{key}_mean": err_r / 100 for key in KEYS} | {"test/err_r_deg_mean": err_r}
    metrics["test/err_r_deg_median"] = err_r / 2
    (folder / "metrics.json").write_text(json.dumps({"metrics": metrics}))
    (folder.parent / f"{folder.name}.seconds").write_text(f"{seconds}\n")
    records = [
        {"step": 0, "val/err_r_deg_mean": 40.0},
        {"step": 10, "train/loss": 1.0},
        {"step": 20, "val/err_r_deg_mean": err_r},
    ]
    (folder / "scalars.jsonl").write_text("\n".join(json.dumps(r) for r in records))
    (folder / "evaluation" / "figures").mkdir(parents=True)
    (folder / "evaluation" / "figures" / "pair_0000.png").write_bytes(b"png")


def test_report_tables_curves_and_figures(tmp_path, capsys):
    out = tmp_path / "reproduce"
    _run(out / "airplane" / "rpm_ours_s1", 2.0, 60)
    _run(out / "airplane" / "rpm_ours_s2", 4.0, 120)
    _run(out / "airplane" / "rpm_cd_s1", 5.0, 60)
    (out / "airplane" / "rpm_gt_s1").mkdir()  # unfinished: no metrics.json, left out
    baselines = out / "airplane" / "baselines"
    baselines.mkdir()
    summary = {f"{key}_mean": 0.5 for key in KEYS} | {"err_r_deg_median": 0.25, "seconds_mean": 0.01}
    (baselines / "results.json").write_text(json.dumps({"summary": {"icp_point": summary}}))
    docs = tmp_path / "docs" / "results"
    page = tmp_path / "docs" / "results.md"
    page.parent.mkdir()
    page.write_text("# Results\n\nintro\n<!-- tables:begin -->\nold\n<!-- tables:end -->\n\noutro\n")
    assert reproduce_report.main([str(out), "--docs", str(docs), "--page", str(page)]) == 0
    table = (docs / "tables.md").read_text()
    assert table.startswith("### Airplane") and "rpm_ours" in capsys.readouterr().out
    lines = [line for line in table.splitlines() if line.startswith("| ")]
    names = [line.split("|")[1].strip() for line in lines[1:]]
    assert names == ["icp_point", "rpm_cd", "rpm_ours"]
    ours = lines[3].split("|")
    assert ours[2].strip() == "3.000 ± 1.414" and ours[6].strip() == "1.673" and ours[8].strip() == "2"
    assert ours[9].strip() == "1.5 min"
    icp = lines[1].split("|")
    assert icp[2].strip() == "0.500" and icp[3].strip() == "5.000, 5.000" and icp[6].strip() == "7.223"
    assert (docs / "curves_airplane.png").stat().st_size > 1000
    assert (docs / "figure_airplane_rpm_ours.png").read_bytes() == b"png"
    filled = page.read_text()
    assert filled.startswith("# Results\n\nintro\n<!-- tables:begin -->\n### Airplane") and "old" not in filled
    assert filled.endswith("<!-- tables:end -->\n\noutro\n") and "](results/curves_airplane.png)" in filled
    assert "](results/figure_airplane_rpm_ours.png)" in filled
