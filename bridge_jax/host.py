"""The machine this process runs on, named for results and model cards: "<cores>-core <CPU model> (<ISA>)"."""

from __future__ import annotations

import os
import platform

from bridge_jax.models import layers


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), else what `platform` says."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def cpu_isa() -> str | None:
    """The widest x86 vector ISA the CPU reports ("AVX-512", "AVX2" or "older"; None off Linux/x86): these
    VMs come as both kinds, and XLA:CPU's convolutions (and so every ratio to PyTorch) differ between them."""
    return layers.cpu_vector_isa()


def machine() -> str:
    """One line naming this machine for results: "<cores>-core <CPU model> (<ISA>)"."""
    isa = cpu_isa()
    return f"{os.cpu_count()}-core {cpu_model()}" + (f" ({isa})" if isa else "")


__all__ = ["cpu_model", "cpu_isa", "machine"]
