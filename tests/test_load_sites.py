"""Every file the project reads back refuses to run code (issue 22, item 1): a planted payload that would write a
file when unpickled never runs, and the refusal is one line naming the file. The checkpoint itself is covered by
tests/training/test_checkpoint.py and test_faults.py; this file covers the other load sites (docs/training.md,
"Checkpoints": the audit)."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from bronchocli.config import load_config
from bronchocli.errors import BronchoError


class WritesAFile:
    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (Path.write_text, (Path(self.marker), "code ran"))


def test_pretrained_weights_with_a_payload_are_refused(tmp_path):
    from bronchocli.models.pretrained import read_state_dict

    marker, path = tmp_path / "pwned", tmp_path / "weights.pt"
    torch.save({"conv.weight": torch.zeros(1), "x": WritesAFile(marker)}, path)
    with pytest.raises(BronchoError) as err:
        read_state_dict(path)
    assert not marker.exists() and str(path) in str(err.value) and "\n" not in str(err.value)


def test_a_frame_cache_holding_pickled_objects_is_never_unpickled(tmp_path):
    from bronchocli.data.cache import FrameCache

    marker, path = tmp_path / "pwned", tmp_path / "frames.npy"
    with open(path, "wb") as fh:  # an object array: np.save pickles its items
        np.save(fh, np.array([WritesAFile(marker)], dtype=object), allow_pickle=True)
    assert not FrameCache._valid(path, (1, 3, 2, 2))  # rebuilt, not read
    with pytest.raises(ValueError, match="allow_pickle|Python objects"):
        FrameCache(path, (1, 3, 2, 2)).array
    assert not marker.exists()


@pytest.mark.parametrize("tag", ["!!python/object/apply:os.system ['touch {m}']",
                                 "!!python/object/new:pathlib.Path ['{m}']"])
def test_a_config_with_python_tags_is_refused_in_one_line(tmp_path, tag):
    marker = tmp_path / "pwned"
    path = tmp_path / "experiments.yaml"
    path.write_text(f"name: {tag.format(m=marker)}\n")
    with pytest.raises(BronchoError) as err:
        load_config(path)
    assert not marker.exists() and str(path.name) in str(err.value)


def test_the_model_artifact_and_checkpoints_are_plain_data(tmp_path):
    from bronchocli.training import checkpoint

    # what `train` writes is what weights_only=True reads: no pickled objects anywhere
    path = checkpoint.save(tmp_path / "last.pt", {"rng": checkpoint.rng_state(), "history": [{"step": 1.0}]})
    assert torch.load(path, weights_only=True)["format"] == checkpoint.FORMAT
    raw = tmp_path / "raw.pt"
    raw.write_bytes(pickle.dumps({"format": checkpoint.FORMAT, "model": WritesAFile(tmp_path / "pwned")}))
    with pytest.raises(checkpoint.BadCheckpoint):
        checkpoint.load(raw)
    assert not (tmp_path / "pwned").exists()


def test_a_model_weights_file_with_a_payload_is_refused_in_one_line(tmp_path):
    import json

    from bronchocli.inference.mlflow_model import load_data_dir
    from bronchocli.training.model_logging import SPEC_FILE, SPEC_FORMAT, SPEC_VERSION, WEIGHTS_FILE

    marker, path = tmp_path / "pwned", tmp_path / WEIGHTS_FILE
    (tmp_path / SPEC_FILE).write_text(json.dumps({"format": SPEC_FORMAT, "version": SPEC_VERSION}))
    torch.save({"state_dict": {"w": torch.zeros(1)}, "x": WritesAFile(marker)}, path)
    with pytest.raises(BronchoError) as err:
        load_data_dir(tmp_path)
    assert not marker.exists() and str(path) in str(err.value) and "\n" not in str(err.value)
