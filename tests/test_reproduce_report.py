"""scripts/reproduce_report.py: tables beside the paper's numbers, seeds, curves, figures."""

from __future__ import annotations

import json

import pytest

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
    assert "](curves_airplane.png)" in table and "](figure_airplane_rpm_ours.png)" in table  # beside tables.md
    assert (docs / "curves_airplane.png").stat().st_size > 1000
    assert (docs / "figure_airplane_rpm_ours.png").read_bytes() == b"png"
    filled = page.read_text()
    assert filled.startswith("# Results\n\nintro\n<!-- tables:begin -->\n### Airplane") and "old" not in filled
    assert filled.endswith("<!-- tables:end -->\n\noutro\n") and "](results/curves_airplane.png)" in filled
    assert "](results/figure_airplane_rpm_ours.png)" in filled


CELLS = """protocol,backbone,loss,recipe,seed,err_r_deg,err_t,median_err_r_deg
airplane,,identity,cpu,,45.0,0.29,44.0
airplane,rpmnet,gt,cpu,0,2.0,,
airplane,rpmnet,gt,cpu,1,2.2,,
airplane,rpmnet,ours,cpu,0,2.4,0.05,1.9
airplane,rpmnet,ours,cpu,1,2.5,,
airplane,rpmnet,ours,cpu,2,2.3,,
airplane,rpmnet,cd,paper,1,4.7,0.14,2.0
airplane,dcp,cd,cpu,0,2.9,,
human,rpmnet,gt,paper,1,2.9,,
"""


def _offsets(ax, gid: str) -> list[tuple[float, float]]:
    return [tuple(xy) for c in ax.collections if c.get_gid() == gid for xy in c.get_offsets()]


def test_figures_from_the_cells_table(tmp_path, capsys):
    table = tmp_path / "cells.csv"
    table.write_text(CELLS)
    figures = tmp_path / "figures"
    assert reproduce_report.main(["--cells", str(table), "--figures", str(figures)]) == 0
    assert sorted(p.name for p in figures.iterdir()) == ["airplane.png"]  # human has no recipe=cpu cell
    assert (figures / "airplane.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert capsys.readouterr().out.strip() == str(figures / "airplane.png")
    cells = reproduce_report.read_cells(table)
    fig = reproduce_report.protocol_figure(cells, "airplane", "cpu")
    rpmnet, dcp = fig.axes
    assert [ax.get_title() for ax in fig.axes] == ["RPM-Net", "DCP"]
    assert [label.get_text() for label in rpmnet.get_xticklabels()] == ["GT", "Ours", "identity"]
    assert sorted(y for _, y in _offsets(rpmnet, "ours")) == [2.3, 2.4, 2.5]  # a dot per seed
    assert len({x for x, _ in _offsets(rpmnet, "ours")}) == 3
    assert _offsets(rpmnet, "paper") == [(0.0, 2.19), (1.0, 1.673)]
    assert _offsets(dcp, "identity") == [(1.0, 45.0)]  # an identity without backbone: every panel
    assert _offsets(dcp, "cd") == [(0.0, 2.9)]
    assert reproduce_report.protocol_figure(cells, "real", "cpu") is None


def test_cells_of_run_folders_merge_into_the_table(tmp_path):
    out = tmp_path / "schedule"
    _run(out / "airplane" / "rpm_ours_s0", 2.0, 60)
    _run(out / "airplane" / "rpm_ours_s1", 4.0, 60)
    _run(out / "airplane" / "rpm_ours_nu2_s0", 3.0, 60)  # not a loss of the table: left out
    metrics = json.loads((out / "airplane" / "rpm_ours_s0" / "metrics.json").read_text())
    metrics["metrics"] |= {f"test/identity/{key}_mean": 0.4 for key in KEYS} | {"test/identity/err_r_deg_median": 40}
    metrics["metrics"]["test/identity/err_r_deg_mean"] = 45.0
    (out / "airplane" / "rpm_ours_s0" / "metrics.json").write_text(json.dumps(metrics))
    table = tmp_path / "cells.csv"
    table.write_text(CELLS)
    argv = [str(out), "--figures", str(tmp_path / "figures"), "--write-cells", str(table)]
    assert reproduce_report.main(argv) == 0
    assert (tmp_path / "figures" / "airplane.png").is_file()
    lines = table.read_text().splitlines()
    assert lines[0] == ",".join(reproduce_report.CELL_COLUMNS) and len(lines) == 1 + 7 + 3
    assert lines[1:8] == [
        line for line in CELLS.splitlines()[1:] if ",ours,cpu,0," not in line and ",ours,cpu,1," not in line
    ]
    assert lines[-3:] == [
        "airplane,rpmnet,ours,cpu,0,2,0.02,1",
        "airplane,rpmnet,ours,cpu,1,4,0.04,2",
        "airplane,rpmnet,identity,cpu,,45,0.4,40",
    ]


def test_a_table_with_another_header_or_a_bad_number_is_refused(tmp_path, capsys):
    table = tmp_path / "cells.csv"
    table.write_text("protocol,loss,err_r_deg\nairplane,gt,2.0\n")
    with pytest.raises(SystemExit) as exit_info:
        reproduce_report.main(["--cells", str(table), "--figures", str(tmp_path)])
    assert exit_info.value.code == 2
    assert "the header must be protocol,backbone,loss,recipe,seed" in capsys.readouterr().err
    table.write_text(CELLS.replace("2.2,,", "2.2 deg,,"))
    with pytest.raises(SystemExit):
        reproduce_report.main(["--cells", str(table), "--figures", str(tmp_path)])
    assert f"{table}, line 4: could not convert string to float: '2.2 deg'" in capsys.readouterr().err
