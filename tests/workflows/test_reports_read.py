"""Reports a person reads (issue 22): `lensdist reproduce` prints a short summary with the
headline table, the rest goes to the report file, and every term is defined where it appears."""

from __future__ import annotations

import json
import re

import torch
from workflow_helpers import tiny_cli_folder

from lensdist_torch.workflows.reports import (
    CANNOT_TELL,
    TERMS,
    evaluate_predictions,
    report_markdown,
    report_summary,
)


def _report() -> dict:
    t = CANNOT_TELL
    fig = evaluate_predictions(
        torch.tensor([0, t, 2, 3, 4, 4, 1]),
        torch.tensor([1.0, float("nan"), 9.0, 12.0, 0.0, 0.0, 3.0]),
        torch.tensor([0, 1, 1, 3, 4, 4, 4]),
        torch.tensor([1.5, 4.0, 4.0, 12.5, 0.0, 0.0, 0.0]),
        delta_range=14.4,
        registration_ok=torch.tensor([True] * 7),
        extra_groups={
            "t_y 0-5 px": torch.tensor([1, 1, 0, 0, 0, 0, 0]),
            "t_y 5-40 px": torch.tensor([0, 0, 1, 1, 1, 1, 1]),
        },
    )
    fig["paper_key"] = "10ev_delta_avg"
    return {
        "title": "lensdist reproduce: the paper's Tables 1 and 2",
        "protocol": "7 test pairs",
        "settings": {"10 EV, delta_avg": fig},
        "unseen": {"scenes": ["brick"], "note": "again on brick", "settings": {"10 EV, delta_avg": fig}},
        "calibration": {"note": "fitted on a validation split", "analysis": {"no_distortion_px": 0.25},
                        "ece": [{"method": "selfcal", "split": "test", "pairs": 7, "before": 0.12, "after": 0.05}]},
    }


def test_the_summary_is_short_and_ends_on_the_report_file():
    text = report_summary(_report(), "out/reproduce.md")
    lines = text.splitlines()
    assert len(lines) <= 20
    assert lines[-1].endswith(": out/reproduce.md")
    row = next(line for line in lines if line.startswith("| 10 EV, delta_avg |"))
    # 4 right of 7 (pairs 0, 3, 4, 5); the paper's 67.8 % beside; R: 2 of the 3 class-R pairs (paper 65 of 100)
    assert row.startswith("| 10 EV, delta_avg | 57.1 % (67.8 %) | 14.3 % | 66.7 % | 2 of 3 (65 of 100) |")
    assert "selfcal 12.0 % -> 5.0 %" in text
    assert "On brick, a scene no method was fitted on, right or cannot tell: 10 EV, delta_avg 71.4 %." in text


def test_the_summary_defines_every_term_of_its_table():
    text = report_summary(_report(), "out/reproduce.md")
    header = next(line for line in text.splitlines() if line.startswith("| setting |"))
    for column in [c.strip() for c in header.strip("|").split("|")][1:]:
        term = column.replace(" (paper)", "")
        assert f"\n{term}: {TERMS[term]}." in text, term
    for term in ("EV", "ECE", "right or cannot tell"):
        assert f"\n{term}: " in text


def _section(md: str, heading: str) -> str:
    start = md.index(heading)
    end = md.find("\n## ", start + 1)
    return md[start : end if end > 0 else len(md)]


def test_the_report_defines_each_term_in_the_section_it_appears_in():
    md = report_markdown(_report())
    table1 = _section(md, "## Table 1")
    for term in ("EV", "R rejected", "cannot tell", "right among confident", "confident wrong", "registration failed"):
        assert f"**{term}**: {TERMS[term]}" in table1, term
    assert "Rate by group (t_y: the vertical translation): t_y 0-5 px: 50.0 % (n=2)" in table1
    assert f"**RMSE**: {TERMS['RMSE']}" in _section(md, "## Table 2")
    assert f"**ECE**: {TERMS['ECE']}" in _section(md, "## Calibration")
    assert "| selfcal | test | 7 | 12.0 % | 5.0 % |" in md
    trust = _section(md, "## Can the answers be trusted?")
    assert f"**right or cannot tell**: {TERMS['right or cannot tell']}" in trust


def test_lensdist_reproduce_prints_the_summary_not_the_report(tiny_run, tmp_path, capsys):
    """The command a user types: its stdout is the summary (the report file is the long one)."""
    from lensdist_torch.cli import main

    out, _ = tiny_run
    tiny_cli_folder(out, tmp_path)
    code = main(
        ["reproduce", "--config", str(tmp_path / "tiny.toml"), "--out", str(tmp_path), "--workers", "1", "--quiet"]
    )
    r = capsys.readouterr()
    assert code == 0, r.err
    lines = r.out.splitlines()
    md = (tmp_path / "reproduce.md").read_text()
    assert len(lines) <= 30 < len(md.splitlines())
    assert lines[-1].endswith(str(tmp_path / "reproduce.md"))
    rep = json.loads((tmp_path / "reproduce.json").read_text())
    rows = [line for line in lines if line.startswith("| ") and not line.startswith("| setting")]
    assert [row.split(" | ")[0][2:] for row in rows] == list(rep["settings"])
    fig = rep["settings"]["10 EV, delta_avg"]
    assert f"{fig['rejected_R']} of {fig['n_R']}" in rows[list(rep["settings"]).index("10 EV, delta_avg")]
    assert "R rejected: class-R test pairs" in r.out and "| truth \\ pred |" not in r.out
    assert len(re.findall(r"\*\*[^*]+\*\*: ", md)) >= 10  # the terms, in the file
