"""``--precision auto`` picks bfloat16 only where PyTorch computes it natively: the CPU's flags are not enough
when PyTorch's kernels or oneDNN are limited to a smaller instruction set."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch
from helpers.paths import REPO as ROOT

from s3k.detector import cpu, training_precision

CPU = torch.device("cpu")


@pytest.fixture
def bf16_silicon(monkeypatch):
    """A CPU whose flags list AVX512-BF16, with PyTorch at AVX-512 and oneDNN uncapped."""
    monkeypatch.setattr(cpu, "cpu_flags", lambda: frozenset({"avx2", "avx512f", "avx512_bf16"}))
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX512")
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    monkeypatch.delenv("DNNL_MAX_CPU_ISA", raising=False)


def test_auto_is_bfloat16_on_a_bf16_cpu_that_pytorch_uses_in_full(bf16_silicon):
    assert cpu.native_bfloat16_cpu()
    assert training_precision("auto", CPU) == "bfloat16"


def test_auto_is_float32_without_the_flags(bf16_silicon, monkeypatch):
    monkeypatch.setattr(cpu, "cpu_flags", lambda: frozenset({"avx2", "fma", "avx512f"}))
    assert training_precision("auto", CPU) == "float32"


def test_auto_is_float32_where_pytorch_kernels_dispatch_below_avx512(bf16_silicon, monkeypatch):
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX2")
    assert training_precision("auto", CPU) == "float32"


@pytest.mark.parametrize("variable", ["ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA"])
@pytest.mark.parametrize("cap, native", [
    ("AVX2", False), ("AVX512_CORE", False), ("avx512_core_vnni", False),
    ("AVX512_CORE_BF16", True), ("AVX512_CORE_AMX", True), ("ALL", True)])
def test_a_onednn_cap_below_avx512_bf16_means_float32(bf16_silicon, monkeypatch, variable, cap, native):
    monkeypatch.setenv(variable, cap)
    assert training_precision("auto", CPU) == ("bfloat16" if native else "float32")
    assert training_precision("bfloat16", CPU) == "bfloat16"  # asked for, it is given


def test_a_process_limited_to_avx2_trains_auto_in_float32():
    """The real variables in a fresh process: PyTorch reports AVX2, and auto resolves to float32 whatever
    the machine's flags."""
    code = ("import torch; from s3k.detector.cpu import isa_limits; "
            "from s3k.detector import training_precision; "
            "print(isa_limits()['aten'], training_precision('auto', torch.device('cpu')))")
    env = dict(os.environ, ATEN_CPU_CAPABILITY="avx2", ONEDNN_MAX_CPU_ISA="AVX2", OMP_NUM_THREADS="1",
               PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["AVX2", "float32"]
