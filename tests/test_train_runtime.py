"""How a training process runs: NCHW memory layout, thread counts, device.

Layout: regression test for the test-suite hang (issue 13): images permuted from (B, H, W, 3) are channels-last
in memory, and oneDNN's 1×1 stride-2 backward-weights kernel for channels-last input with fewer input
channels than its register block writes past its workspace (uxlfoundation/oneDNN#6035).  Depending on
what it overwrote, training hung for good inside ``GOMP_parallel``, crashed, or got wrong gradients.
The case runs in a subprocess because the failure mode is a hang or a segfault of the whole process.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest
import torch

from risp_train.model import ModelConfig, build_model
from risp_train.normalization import Normalization

# A width-4 ResNet (the tests' size) whose first 1×1 stride-2 shortcut sees 4 input channels at 128×128:
# with channels-last input this segfaulted at the first backward on a 2-core AVX2 machine.
SCRIPT = textwrap.dedent("""
    import torch
    from risp_train.model import ModelConfig, build_model
    torch.set_num_threads(2)
    net = build_model(ModelConfig(out_dim=3, width=4, blocks=(1, 1), stem="small"), seed=0)
    x = torch.randn(32, 3, 128, 128, generator=torch.Generator().manual_seed(0))
    conv = net.stages[1][0].shortcut[0]
    net(x.contiguous(memory_format=torch.channels_last)).square().sum().backward()
    g = conv.weight.grad.clone()
    net.zero_grad()
    with torch.backends.mkldnn.flags(enabled=False):  # reference: PyTorch's own convolution
        net(x).square().sum().backward()
    ref = conv.weight.grad
    print("REL", float((g - ref).abs().max() / ref.abs().max()))
""")


def test_channels_last_input_trains_like_nchw():
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, f"exit {r.returncode}: {r.stderr[-2000:]}"
    rel = float(r.stdout.split("REL")[-1])
    assert rel < 1e-5, rel


def test_normalized_inputs_and_tangents_are_nchw_contiguous():
    norm = Normalization(image_mean=(0.1, 0.2, 0.3), image_std=(1.0, 2.0, 3.0),
                         target_mean=(0.0,), target_std=(1.0,))
    img = torch.rand(2, 8, 8, 3)
    x = norm.images(img)
    assert x.shape == (2, 3, 8, 8) and x.is_contiguous()
    dx = norm.tangents(img, torch.rand(2, 5, 8, 8, 3))
    assert dx.shape == (2, 5, 3, 8, 8) and dx.is_contiguous()


def test_forward_is_layout_independent():
    net = build_model(ModelConfig(out_dim=2, width=4, blocks=(1, 1), stem="small"), seed=1)
    x = torch.randn(2, 3, 16, 16, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(net(x.contiguous(memory_format=torch.channels_last)), net(x), rtol=0, atol=0)


# -- thread counts (issue 8, item 5) -------------------------------------------------------------------------
def test_default_threads_leave_a_cpu_per_worker(monkeypatch):
    from risp_data import threads

    monkeypatch.setattr(threads, "available_cpus", lambda: 2)
    assert threads.default_torch_threads(workers=2) == 1  # the shared 2-core machine: one thread
    assert threads.default_torch_threads(workers=0) == 2
    monkeypatch.setattr(threads, "available_cpus", lambda: 16)
    assert threads.default_torch_threads(workers=2) == 14
    assert threads.default_torch_threads(workers=2, processes=2) == 6  # two ranks, two workers each


def test_set_torch_threads_applies_and_validates():
    from risp_data.errors import RispError
    from risp_data.threads import set_torch_threads

    before = torch.get_num_threads()
    try:
        assert set_torch_threads(1) == 1 and torch.get_num_threads() == 1
        with pytest.raises(RispError, match="--threads"):
            set_torch_threads(-1)
    finally:
        torch.set_num_threads(before)


# -- device --------------------------------------------------------------------------------------------------
def test_device_resolution_and_errors():
    from risp_data.errors import RispError
    from risp_train.train import resolve_device

    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(RispError, match="unknown --device"):
        resolve_device("tpu:x")
    if not torch.cuda.is_available():
        with pytest.raises(RispError, match="no CUDA GPU"):
            resolve_device("cuda")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_batch_tensors_on_gpu():
    from risp_data.envs import get_environment
    from risp_train.train import batch_tensors

    env = get_environment("cube")
    norm = Normalization(image_mean=(0.1,) * 3, image_std=(1.0,) * 3, target_mean=(0.0,) * env.target_dim,
                         target_std=(1.0,) * env.target_dim)
    import numpy as np

    batch = {"image": torch.rand(2, 8, 8, 3), "jacobian": torch.rand(2, 4, 8, 8, 3),
             "state": torch.as_tensor(env.sample_states(np.random.default_rng(0), 2))}
    x, y, t = batch_tensors(batch, norm, env, True, torch.device("cuda"))
    assert x.is_cuda and y.is_cuda and t.is_cuda
