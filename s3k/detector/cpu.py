"""What this process's CPU computes natively: its flags, and whether bfloat16 runs on bfloat16 instructions.

``--precision auto`` trains in bfloat16 only where the CPU multiplies bfloat16 natively (AVX512-BF16 or AMX);
elsewhere PyTorch emulates bfloat16 and it is slower than float32. The CPU's flags (``/proc/cpuinfo``) say
what the silicon has, but not what PyTorch will use: its own kernels dispatch by
``torch.backends.cpu.get_cpu_capability()`` (lowered with ``ATEN_CPU_CAPABILITY``, e.g. ``avx2``) and its
convolutions run in oneDNN, whose instruction set ``ONEDNN_MAX_CPU_ISA`` (or the older ``DNNL_MAX_CPU_ISA``)
caps, e.g. ``AVX2``. A process so limited, or a virtual machine's CPU that lists the flags but gives PyTorch
less, computes bfloat16 the emulated way, and is told so here.
"""

from __future__ import annotations

import os

import torch

__all__ = ["BF16_FLAGS", "cpu_flags", "isa_limits", "native_bfloat16_cpu"]

BF16_FLAGS = frozenset({"avx512_bf16", "amx_bf16"})
"""The ``/proc/cpuinfo`` flags of a CPU with bfloat16 arithmetic."""

# oneDNN's names of the instruction sets (ONEDNN_MAX_CPU_ISA) that include bfloat16 arithmetic: AVX512-BF16
# and what comes after it on that line (AVX512-FP16, AMX, AVX10); "ALL" (and "DEFAULT") lift the cap
_ONEDNN_BF16_ISAS = ("AVX512_CORE_BF16", "AVX512_CORE_FP16", "AVX512_CORE_AMX", "AVX10", "ALL", "DEFAULT")


def cpu_flags() -> frozenset[str]:
    """The flags of the first processor in ``/proc/cpuinfo`` (empty where there is no such file)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("flags"):
                    return frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    return frozenset()


def isa_limits() -> dict[str, str | None]:
    """What PyTorch dispatches to in this process: ``aten`` (``get_cpu_capability()``: ``"AVX512"``,
    ``"AVX2"``, ``"DEFAULT"``, ...) and ``onednn``, the cap set by ``ONEDNN_MAX_CPU_ISA`` or
    ``DNNL_MAX_CPU_ISA`` (None: no cap)."""
    onednn = os.environ.get("ONEDNN_MAX_CPU_ISA") or os.environ.get("DNNL_MAX_CPU_ISA")
    return {"aten": torch.backends.cpu.get_cpu_capability(), "onednn": onednn.upper() if onednn else None}


def native_bfloat16_cpu() -> bool:
    """Whether this process computes bfloat16 natively on the CPU: the CPU's flags include AVX512-BF16 or
    AMX-BF16, PyTorch's kernels dispatch to AVX-512, and oneDNN is not capped below AVX512-BF16."""
    if not cpu_flags() & BF16_FLAGS:
        return False
    limits = isa_limits()
    if not str(limits["aten"]).upper().startswith("AVX512"):
        return False
    cap = limits["onednn"]
    return cap is None or cap.startswith(_ONEDNN_BF16_ISAS)
