"""Execution options of the learner: precision, compilation and CUDA graphs.

None of these changes the method (docs/methods.md): ``precision = "bf16"`` changes only the number
format of the networks' matrix products, ``compile`` and ``cuda_graphs`` change only how the same
operations are executed. They apply to the gradient updates of pre-training (:class:`FBAgent`,
:class:`DVFBAgent`); acting, inference and fine-tuning always run eagerly in float32.

What each option does, and the defaults (see bench/README.md for the measurements behind them):

* ``precision``:

  * ``fp32`` (default) -- everything in float32.
  * ``bf16`` -- every network forward of an update runs under ``torch.autocast(dtype=bfloat16)``:
    its matrix products (Linear, bmm/baddbmm) take bfloat16 inputs with float32 accumulation
    (Intel AMX / tensor cores), and its activations between layers are bfloat16. Each network's
    output is cast back to float32 before it is used, so every loss, every reduction (the N x N
    FB/TM matrices, the Gram matrix, the covariance solve, the NCE and CE similarity matrices,
    the running statistics) and every optimiser state stays float32, as do the parameters
    (autocast casts copies). Off by default: a short DVFB pre-training (walker, small preset, two
    seeds; docs/results/precision_check.md) put 11 of 14 logged training curves within seed noise
    of fp32 but not the orthonormality loss, the FB diagonal term and the exploration critic's
    loss. Speed (bench/README.md, 2-core AMX CPU, 2 threads): the paper-size DVFB update takes
    about half to two thirds of the fp32 time; at the small preset bf16 is no faster.

* ``compile`` -- ``torch.compile`` each network used by the update (online and target). The loss
  code, the optimiser steps and acting stay eager. Compilation happens on the first update (tens
  of seconds per network on a small CPU); if ``torch.compile`` fails while compiling a network,
  a warning is logged and every network falls back to eager execution. Off by default: on the
  development CPU the compiled DVFB update is slower than eager (hidden 256: 99.8 ms against
  50.1 ms, its matrix products alone twice as slow; small preset about 1.4x slower), after a
  first update of ~20-70 s. Re-measure with ``bench/learner.py --compile --compile-configs ...``.

* ``cuda_graphs`` -- CUDA only: compile the networks with ``mode="reduce-overhead"``, i.e. replay
  them as CUDA graphs, removing per-kernel launch overhead at small sizes. Implies ``compile``.
  Requesting it for a CPU run raises :class:`ConfigError`.
"""

from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass
from typing import Any, Callable

import torch
from torch import nn

from dvfb.core.config import param
from dvfb.core.errors import ConfigError
from dvfb.nets import full_precision

log = logging.getLogger(__name__)

PRECISIONS = ("fp32", "bf16")


@dataclass
class PerfConfig:
    """How the learner executes; none of these options changes the method (issue "Performance")."""

    precision: str = param("fp32", "Number format of the networks' matrix products in an update: fp32, or bf16 "
                           "autocast (losses, reductions, parameters and optimiser states stay fp32).",
                           PRECISIONS)
    compile: bool = param(False, "torch.compile the networks used by the update (falls back to eager with a "
                          "warning if compilation fails).")
    cuda_graphs: bool = param(False, "CUDA only: replay the compiled networks as CUDA graphs "
                              "(torch.compile mode 'reduce-overhead'); implies compile.")
    tf32: bool = param(False, "CUDA only: let float32 matrix products and convolutions use TensorFloat-32 "
                       "(faster on Ampere and newer GPUs, about 3 significant digits per product). Off: fp32 "
                       "means IEEE float32 on every device, so that GPU and CPU runs agree to float32 rounding.")


def set_tf32(enabled: bool) -> None:
    """Set whether CUDA's float32 matrix products and cuDNN's convolutions may use TF32 (torch's
    process-wide switches; cuDNN's convolutions default to TF32, so "off" has to be said)."""
    mode = "tf32" if enabled else "ieee"
    torch.backends.cuda.matmul.fp32_precision = mode
    torch.backends.cudnn.conv.fp32_precision = mode


def bf16_matmul_is_fast(device: torch.device) -> bool:
    """Whether bfloat16 matrix products have hardware support here (AMX/AVX512-BF16 or a GPU)."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # pragma: no cover - build without oneDNN
        return False


class NetRunner:
    """Calls a network the way the update should run it: in the configured precision, compiled or not.

    ``runner(net, *inputs)`` returns ``net(*inputs)`` as float32. In fp32 without compilation that
    is exactly ``net(*inputs)`` (no copy, no context switch).
    """

    def __init__(self, config: PerfConfig | None, device: torch.device | str):
        self.config = config if config is not None else PerfConfig()
        self.device = torch.device(device)
        c = self.config
        if c.precision not in PRECISIONS:
            raise ConfigError(f"perf.precision must be one of {PRECISIONS}, got {c.precision!r}")
        if c.cuda_graphs and self.device.type != "cuda":
            raise ConfigError(f"perf.cuda_graphs needs a CUDA device; this run uses {self.device}. "
                              "Use --perf.cuda-graphs false (CUDA graphs do not exist on CPU).")
        if c.tf32 and self.device.type != "cuda":
            raise ConfigError(f"perf.tf32 applies to CUDA matrix products only; this run uses {self.device}. "
                              "Use --perf.tf32 false.")
        if self.device.type == "cuda":
            set_tf32(c.tf32)
        self.autocast_dtype = torch.bfloat16 if c.precision == "bf16" else None
        if self.autocast_dtype is not None and not bf16_matmul_is_fast(self.device):
            log.warning("perf.precision=bf16 on %s without hardware bfloat16 matrix support: it will "
                        "likely be slower than fp32", self.device)
        self.compile_enabled = bool(c.compile or c.cuda_graphs)
        self._compiled: dict[int, Callable] = {}

    def __deepcopy__(self, memo):
        # Compiled callables belong to the original networks; a copy (of an agent) runs eagerly
        # with the same precision.
        copy = NetRunner(self.config, self.device)
        copy.compile_enabled = False
        return copy

    # Compilation ----------------------------------------------------------------------------------
    def compile(self, modules: list[nn.Module]) -> None:
        """Register compiled versions of ``modules`` (compilation itself happens at the first call)."""
        if not self.compile_enabled:
            return
        mode = "reduce-overhead" if self.config.cuda_graphs else None
        # Networks of one class share their forward's code object, and dynamo's per-code-object
        # cache (8 entries by default) would otherwise overflow and silently fall back to eager.
        dynamo_config = getattr(getattr(torch, "_dynamo", None), "config", None)
        for name in ("recompile_limit", "cache_size_limit"):
            if dynamo_config is not None and hasattr(dynamo_config, name):
                setattr(dynamo_config, name, max(getattr(dynamo_config, name), 8 * len(modules)))
        for module in modules:
            try:
                # Static shapes: every network sees one or two fixed batch sizes in an update.
                self._compiled[id(module)] = torch.compile(module, mode=mode, dynamic=False)
            except Exception as exc:  # noqa: BLE001 - any failure means: run eagerly
                self._disable_compilation(exc)
                return

    def _disable_compilation(self, exc: BaseException) -> None:
        log.warning("torch.compile failed (%s: %s); running the networks eagerly", type(exc).__name__,
                    str(exc).splitlines()[0] if str(exc) else "")
        self._compiled.clear()
        self.compile_enabled = False

    @property
    def compiled(self) -> bool:
        """Whether any network currently runs compiled."""
        return bool(self._compiled)

    # Calling --------------------------------------------------------------------------------------
    def autocast(self) -> contextlib.AbstractContextManager:
        if self.autocast_dtype is None:
            return contextlib.nullcontext()
        return torch.autocast(self.device.type, dtype=self.autocast_dtype)

    def _call(self, net: nn.Module, args: tuple) -> Any:
        fn = self._compiled.get(id(net))
        if fn is None:
            return net(*args)
        try:
            return fn(*args)
        except Exception as exc:  # noqa: BLE001
            # Compilation errors surface at the first call, before the network has computed
            # anything, so running the same call eagerly is exact.
            if not _is_compile_error(exc):
                raise
            self._disable_compilation(exc)
            return net(*args)

    def __call__(self, net: nn.Module, *args: Any) -> torch.Tensor:
        if self.autocast_dtype is None:
            return self._call(net, args)
        with self.autocast():
            out = self._call(net, args)
        return full_precision(out)


def _is_compile_error(exc: BaseException) -> bool:
    """Whether ``exc`` comes from torch.compile's machinery rather than from the computation."""
    module = type(exc).__module__ or ""
    if module.startswith(("torch._dynamo", "torch._inductor", "torch._functorch")):
        return True
    # Inductor wraps C++ compiler failures and missing toolchains in these exception types.
    return type(exc).__name__ in ("BackendCompilerFailed", "CppCompileError", "InductorError",
                                  "InvalidCxxCompiler", "Unsupported")


@contextlib.contextmanager
def requires_grad_disabled(params: list[nn.Parameter]):
    """Temporarily stop autograd from tracking ``params`` (those that require grad on entry).

    Used for the actor loss (§7.11), which differentiates through F and Q_P only with respect to
    the action: the graph then omits everything that only leads to their parameters.
    """
    params = [p for p in params if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in params:
            p.requires_grad_(True)


DEVICES = ("auto", "cpu", "cuda")


def resolve_device(device: str) -> torch.device:
    """A run's ``--device``: ``auto`` picks CUDA when torch sees it; anything but :data:`DEVICES` is
    refused in one line (the Python API passes what its caller typed)."""
    if device not in DEVICES:
        raise ConfigError(f"device {device!r} is not one of {', '.join(DEVICES)}")
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' was requested but torch sees no CUDA device; use --device cpu or auto")
    return torch.device(device)
