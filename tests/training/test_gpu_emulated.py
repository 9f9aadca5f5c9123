"""Every CUDA branch of the loop, run on the CPU: each architecture in each precision, resident frames,
accumulation, truncated BPTT, non-finite losses, checkpoint and bitwise resume, host syncs, compilation.

What differs on CUDA is the device type; what the loop does in each precision (autocast dtype, the loss
scaler, skipped-step counting, the device-side loss and non-finite bookkeeping, frames gathered from a
device-resident bank) runs here on the CPU with the same code. Inputs are tiny (16 px, 32 for OffsetNet; 2-4 steps).
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import torch

from bronchocli.data.batches import FrameSource
from bronchocli.diagnostics import selftest
from bronchocli.diagnostics.dispatch import OpCounter
from bronchocli.models import ARCHITECTURES
from bronchocli.training import checkpoint
from bronchocli.training.loop import AMP_GROWTH_INTERVAL, NonFiniteLoss, NothingTrained, Settings, Trainer

PRECISIONS = ("32", "bf16-mixed", "16-mixed")
SIZE = 16  # the smallest input the models take: every check here is about the loop, not the pixels
# ... except where the CPU kernels are not deterministic at 16 px. A dense 3x3 stride-2 convolution on a 1x1
# map (OffsetNet's ResNet-34 layer4.0.conv1 at 16 px) in bf16 autocast, channels_last: oneDNN's backward
# leaves the weight gradient of the 8 taps that see only padding uninitialised (whatever the memory held:
# 0, garbage like 4e37, or NaN, differing from one call to the next on identical inputs), so two identical
# straight runs already differ. At 32 px that conv sees 2x2 and its backward is deterministic. The other
# architectures' strided convolutions on 1x1 maps are depthwise, whose backward is deterministic.
SIZES = {"offsetnet": 32}


def size_of(arch: str) -> int:
    return SIZES.get(arch, SIZE)


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return selftest.synthetic_cache(tmp_path_factory.mktemp("frames"), frames=16, size=SIZE)


@pytest.fixture(scope="module")
def caches(tmp_path_factory, cache):
    sizes = {size: selftest.synthetic_cache(tmp_path_factory.mktemp(f"frames{size}"), frames=16, size=size)
             for size in set(SIZES.values()) - {SIZE}}
    return {SIZE: cache, **sizes}


_PRISTINE: dict[tuple[str, int], torch.nn.Module] = {}


def loop_trainer(arch: str, precision: str, cache, steps: int, ckpt: Path | None = None,
                 bad_label: bool = False) -> Trainer:
    """2 micro-batches per step (accumulation); temporal models: samples of 2 pairs in 2 TBPTT chunks of 1."""
    size = cache.shape[-1]
    if (arch, size) not in _PRISTINE:  # one initialisation per architecture: building the backbones is slow
        torch.manual_seed(0)
        _PRISTINE[arch, size] = selftest.network(arch, torch.device("cpu"), size)
    net = copy.deepcopy(_PRISTINE[arch, size])
    temporal = ARCHITECTURES[arch].temporal
    pairs = 2 if temporal else 1
    train = selftest.synthetic_samples(4, pairs, len(cache), seed=1)
    val = selftest.synthetic_samples(2, pairs, len(cache), seed=2)
    if bad_label:
        train.labels[:, 0, 0] = np.inf
    s = Settings(steps=steps, micro_pairs=2 * pairs if temporal else 2, accum=2, chunk=1, val_every=1,
                 patience=None, min_delta=0.0, lr=1e-3, weight_decay=0.0, warmup_steps=0, schedule="constant",
                 rot_loss="ce", rot_weight=1.0, precision=precision, bn_recalibrate=1, augment=True, seed=0)
    source = FrameSource(cache, "cpu", "yes")
    assert source.resident  # the device-resident gather path, as on CUDA
    t = Trainer(net, train, val, source, s, device=torch.device("cpu"), ckpt_dir=ckpt)
    if precision == "16-mixed":
        # CPU fp16 convolutions accumulate weight gradients in fp16: the first conv's reaches ~7e4 (> 65504)
        # at any scale >= 1, where CUDA accumulates in fp32. Start below it so the short run takes steps.
        t.scaler = torch.amp.GradScaler("cpu", init_scale=2.0**-6, growth_interval=AMP_GROWTH_INTERVAL)
    return t


def _fit(t: Trainer) -> str:
    """Fit; on the CPU, 16-mixed may skip every step (fp16 CPU kernels overflow where CUDA's accumulate in
    fp32): then the outcome is the loud NothingTrained, which must be the same straight and resumed."""
    try:
        t.fit()
    except NothingTrained as exc:
        return str(exc)
    return "trained"


# Every architecture in bf16-mixed (the CUDA default) and two (one pairwise, one recurrent) in 32 and 16-mixed
# in CI; the other six combinations are `slow` (about 10 s each of CPU time).
FAST = {(a, "bf16-mixed") for a in ARCHITECTURES} | {(a, p) for a in ("baseline", "convlstm") for p in PRECISIONS}
MATRIX = [pytest.param(a, p, marks=() if (a, p) in FAST else pytest.mark.slow, id=f"{a}-{p}")
          for a in ARCHITECTURES for p in PRECISIONS]


@pytest.mark.parametrize(("arch", "precision"), MATRIX)
def test_the_loop_trains_checkpoints_and_resumes_bitwise_in_every_precision(arch, precision, caches, tmp_path):
    cache = caches[size_of(arch)]
    straight = loop_trainer(arch, precision, cache, steps=2, ckpt=tmp_path)
    straight._train_until(1)
    straight._validation()  # what fit() does after each interval: here it writes last.pt at step 1
    straight.ckpt_dir = None
    outcome = _fit(straight)  # ... and carries on, uninterrupted, to step 2
    assert straight.step == 2 and straight.micro == (2 if ARCHITECTURES[arch].temporal else 4)  # accumulation, TBPTT
    if precision != "16-mixed":
        assert outcome == "trained" and straight.skipped_steps == 0

    resumed = loop_trainer(arch, precision, cache, steps=2)
    with torch.no_grad():
        for p in resumed.net.parameters():
            p.add_(1.0)  # load_state must replace everything
    torch.manual_seed(99)
    resumed.load_state(checkpoint.load(tmp_path / "last.pt"))
    assert _fit(resumed) == outcome
    a, b = straight.net.state_dict(), resumed.net.state_dict()
    differ = [k for k in a if not torch.equal(a[k], b[k])]  # bitwise (a NaN anywhere fails)
    assert differ == []
    # train.core_s: CPU seconds the steps took (the cost of learning), a measurement, not training state
    measured = lambda h: {k: v for k, v in h.items() if k != "train.core_s"}  # noqa: E731
    assert measured(resumed.history[-1]) == measured(straight.history[-1]) or precision != "32"
    assert resumed.history[-1]["train_loss"] == straight.history[-1]["train_loss"] or outcome != "trained"
    assert resumed.micro == straight.micro and resumed.skipped_steps == straight.skipped_steps


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("arch", ["baseline", "convlstm"])
def test_a_non_finite_loss_fails_the_run_in_every_precision(arch, precision, cache):
    t = loop_trainer(arch, precision, cache, steps=2, bad_label=True)
    with pytest.raises(NonFiniteLoss, match="non-finite training loss by step 1"):
        t.fit()


@pytest.mark.parametrize("arch", ["baseline", "lstm"])
def test_a_steady_state_step_makes_no_host_sync_and_a_validation_few(arch, cache):
    t = loop_trainer(arch, "bf16-mixed", cache, steps=6)
    t.check_every = 25  # as on CUDA: the non-finite check is a host sync every 25 steps
    t._train_until(1)  # warm-up: lazy optimiser state
    with OpCounter() as steps:
        t._train_until(3)
    assert steps.syncs == 0, steps.by_name
    with OpCounter() as validation:
        t._validation()
    # validate's one .tolist(), the train-loss/skipped read, the non-finite check, and lr/epoch (host floats)
    assert 0 < validation.syncs <= 4, validation.by_name


@pytest.mark.parametrize("arch", ["offsetnet", pytest.param("baseline", marks=pytest.mark.slow)])
def test_a_pairwise_model_compiles_to_one_graph_without_breaks(arch):
    net = selftest.network(arch, torch.device("cpu"), SIZE)
    frames = torch.randint(0, 256, (2, 2, 3, SIZE, SIZE), dtype=torch.uint8)
    explained = torch._dynamo.explain(net)(frames)
    assert explained.graph_break_count == 0, [str(b.reason) for b in explained.break_reasons]
    assert explained.graph_count == 1


def test_compile_modes_are_checked_and_a_codegen_free_backend_runs_the_step():
    from bronchocli.errors import BronchoError
    from bronchocli.training.loop import compile_network

    net = torch.nn.Linear(3, 2)
    assert compile_network(net, False) is net
    with pytest.raises(BronchoError, match="train.compile 'fast'"):
        compile_network(net, "fast")
    graphs = []

    def counting(gm, example_inputs):
        graphs.append(gm)
        return gm.forward

    torch._dynamo.reset()
    compiled = compile_network(net, "reduce-overhead", backend=counting)
    x = torch.randn(4, 3)
    compiled(x).sum().backward()
    compiled(x)
    assert len(graphs) == 1 and net.weight.grad is not None  # one capture, replayed


def test_the_uncounted_batchnorm_matches_pytorchs_without_the_per_batch_counter():
    from torch import nn

    from bronchocli.models.backbones import BatchNorm2d

    torch.manual_seed(0)
    ours, theirs = BatchNorm2d(4), nn.BatchNorm2d(4)
    theirs.load_state_dict(ours.state_dict())  # same keys: torchvision checkpoints load
    x = torch.randn(6, 4, 5, 5)
    assert torch.equal(ours(x), theirs(x))
    assert torch.equal(ours.running_mean, theirs.running_mean) and torch.equal(ours.running_var, theirs.running_var)
    assert int(ours.num_batches_tracked) == 0 and int(theirs.num_batches_tracked) == 1
    ours.eval(), theirs.eval()
    assert torch.equal(ours(x), theirs(x))
    ours.train()
    ours.momentum = None  # PyTorch's cumulative mode needs the counter: then the layer is PyTorch's own
    ours(x)
    assert int(ours.num_batches_tracked) == 1


# Operations one steady-state bf16 optimiser step of 4 pairs dispatched before issue 21 (benchmarks/README.md).
OPS_BEFORE = {"baseline": 2807, "offsetnet": 1267}


@pytest.mark.parametrize(("arch", "cut"), [("baseline", 0.10), ("offsetnet", 0.05)])
def test_a_step_dispatches_fewer_operations_than_before(arch, cut, cache):
    from bronchocli.diagnostics.dispatch import count_step

    t = selftest.trainer(arch, torch.device("cpu"), "bf16-mixed", cache, steps=6)
    t.check_every = 25
    ops = count_step(t)
    assert ops.syncs == 0
    assert ops.total <= (1 - cut) * OPS_BEFORE[arch], ops.summary()
