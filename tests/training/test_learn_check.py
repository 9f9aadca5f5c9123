"""`bronchopose selftest --learn`: memorise a handful of the dataset's pairs through the platform's path, and
check that evaluation reproduces training; one line per architecture, exit 1 when one cannot."""

from __future__ import annotations

import re


def verdict(out: str) -> tuple[float, float]:
    text = " ".join(out.split())
    m = re.search(r"to ([0-9.]+) x the training-mean predictor's loss .* gap ([0-9.]+)", text)
    assert m, text
    return float(m.group(1)), float(m.group(2))


def test_the_baseline_memorises_the_tiny_dataset_and_evaluation_reproduces_it(tiny_project, cli, monkeypatch):
    monkeypatch.chdir(tiny_project)
    code, out, err = cli("selftest", "--learn", "-a", "baseline", "--steps", "40", "--threads", "1")
    overfit, gap = verdict(out)
    assert code == 0, out + err
    assert "baseline can learn here" in " ".join(out.split())
    assert overfit <= 0.3 and gap <= 1.10


def test_a_model_that_cannot_move_its_weights_is_said_not_to_learn(tiny_project, cli, monkeypatch):
    monkeypatch.chdir(tiny_project)
    code, out, err = cli("selftest", "--learn", "-a", "baseline", "--steps", "5", "--threads", "1",
                         "--set", "train.lr=1e-9")
    overfit, _ = verdict(out)
    assert code == 1, out + err
    assert "baseline cannot be shown to learn here" in " ".join(out.split())
    assert overfit > 0.3
