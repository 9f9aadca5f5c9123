"""Device diagnostic (benchmarks/README.md, "GPU device check"): why selftest's resume check differed on CUDA.

    python benchmarks/resume_diag.py [ARCH ...]      # default convlstm baseline; CUDA when there is one

Prints, per variant (bf16 or fp32, faked device count, deterministic cuDNN), the validation history of an
uninterrupted run and of a run saved at step 2 and resumed, and the tensors that differ most.
"""
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import torch

from bronchocli.diagnostics import selftest as st
from bronchocli.training import checkpoint

dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")


def run(arch, precision, fake, det):
    torch.backends.cudnn.deterministic = det
    torch.backends.cudnn.benchmark = not det
    tmp = Path(tempfile.mkdtemp())
    cache = st.synthetic_cache(tmp)
    straight = st.trainer(arch, dev, precision, cache, steps=4)
    straight.fit()
    first = st.trainer(arch, dev, precision, cache, steps=4, ckpt_dir=tmp / "c")
    first.s = replace(first.s, steps=2)
    if fake:
        with st.visible_devices(8):
            first.fit()
    else:
        first.fit()
    state = checkpoint.load(tmp / "c" / "last.pt")
    second = st.trainer(arch, dev, precision, cache, steps=4, init_seed=123)
    second.load_state(state)
    second.fit()
    a, b = straight.net.state_dict(), second.net.state_dict()
    diffs = sorted(((a[k].double() - b[k].double()).abs().max().item(), k) for k in a if a[k].is_floating_point())
    hs = [(h["step"], round(h["val_loss"], 6)) for h in straight.history]
    hr = [(h["step"], round(h["val_loss"], 6)) for h in second.history]
    print(f"{arch} {precision} fake8={fake} det={det}: best straight {straight.best_step} resumed {second.best_step}; "
          f"val straight {hs} resumed {hr}; worst {diffs[-3:]}", flush=True)


for arch in sys.argv[1:] or ["convlstm", "baseline"]:
    for precision, fake, det in [("bf16-mixed", True, False), ("bf16-mixed", False, False), ("32", False, True),
                                 ("bf16-mixed", False, True)]:
        try:
            run(arch, precision, fake, det)
        except Exception as e:  # noqa: BLE001
            print(arch, precision, fake, det, "ERROR", type(e).__name__, e, flush=True)
