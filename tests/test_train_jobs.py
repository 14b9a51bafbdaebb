"""``stack-train drl``'s flags come from one place, the DrlJob dataclass (CleanRL style)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import pytest

from stack.train import cli
from stack.train.drl import HELD_OUT_SEED, DrlJob, add_arguments
from stack.train.flags import field_docs, job_from_args


def _parse(*argv):
    p = argparse.ArgumentParser()
    add_arguments(p)
    return job_from_args(DrlJob, p.parse_args(list(argv))), p


def test_every_field_has_a_docstring_and_a_flag():
    docs = field_docs(DrlJob)
    _, p = _parse()
    helps: dict[str, list[str]] = {}
    for a in p._actions:
        helps.setdefault(a.dest, []).append(" ".join((a.help or "").split()))
    for f in dataclasses.fields(DrlJob):
        assert docs.get(f.name), f"DrlJob.{f.name} has no docstring"
        if f.metadata.get("cli", True):
            assert any(docs[f.name] in h for h in helps.get(f.name, [])), f.name
    assert "extra" not in helps


def test_no_flags_is_the_dataclass_default():
    job, _ = _parse()
    assert job == DrlJob()
    assert job.episodes == 5000 and DrlJob(stage=2).episodes == 10000 and job.eval_seed == HELD_OUT_SEED


def test_flags_reach_their_fields():
    job, _ = _parse("--stage", "2", "--walls", "0", "--mse", "--no-progress", "--no-plots", "--episodes", "7",
                    "--time-penalty", "0.01", "--init", "w.pt", "--eps-start", "0.3", "--robots", "5")
    assert (job.stage, job.max_walls, job.huber, job.progress, job.plots, job.episodes) == (2, 0, False, False, False, 7)
    assert job.time_penalty == 0.01 and job.init == Path("w.pt") and job.eps_start == 0.3 and job.robots == 5
    assert _parse("--no-huber")[0].huber is False and _parse("--huber")[0].huber is True


@pytest.mark.parametrize("argv, words", [(["--envs", "0"], "--envs"), (["--walls", "9"], "--walls"),
                                         (["--time-penalty", "-1"], "--time-penalty"), (["--bogus"], "--bogus")])
def test_bad_flags_are_one_line_exit_2(argv, words, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["drl", *argv])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err


def test_missing_weights_are_one_line_exit_2(tmp_path, capsys):
    assert cli.main(["drl", "--evaluate", str(tmp_path / "none.pt")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "none.pt: no such weights file" in err
