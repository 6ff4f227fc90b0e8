"""``torch.compile`` (Inductor) for training (``trainer.compile=true``) and inference (``omnidl predict --compile``).

Training: :func:`compile_for_training` wraps the model of the training step (after the DDP wrapper, so
TorchDynamo's DDP optimiser splits the graph at the gradient buckets) in ``torch.compile`` with Inductor's
default mode. The compiled module shares its parameters with the plain model, so optimiser, checkpoints (the
plain model's state dict: no ``_orig_mod.`` prefix), resume and validation (the plain model, eager) are
unchanged. ``torch.compile`` is lazy: the graphs are traced and compiled during the first training step
(forward at its first call, backward at its first backward). :class:`CompileTimer` measures that step and
the next one and logs the difference as the compile time (what the first step cost beyond a compiled step).

Inference: :func:`compile_for_inference` compiles an eval-mode model with Inductor's ``freezing``
(weights folded into the graph as constants; it needs calls under ``torch.no_grad()``, which
:class:`FrozenInference` makes, as ``omnidl predict`` does anyway).

:func:`check_inductor` refuses, with the option named, a platform where Inductor cannot work: an unsupported
Python, no C++ compiler (CPU), no Triton or a GPU older than compute capability 7.0 (CUDA).
"""
from __future__ import annotations

import importlib
import logging
import time

import torch

log = logging.getLogger("omnidl.engine")


class CompileUnavailable(RuntimeError):
    """``torch.compile`` with Inductor cannot run on this platform/torch (the message says why)."""


def inductor_problem(device: torch.device | str) -> str | None:
    """Why Inductor cannot compile for ``device`` here, or None when it can (as far as can be told without
    compiling anything)."""
    device = torch.device(device)
    if not hasattr(torch, "compile"):
        return f"torch {torch.__version__} has no torch.compile (PyTorch 2.0 or newer needed)"
    try:
        from torch._dynamo.eval_frame import check_if_inductor_supported
        check_if_inductor_supported()
    except ImportError:
        pass
    except Exception as e:  # unsupported Python (version, free-threaded build) or platform
        return str(e) or type(e).__name__
    try:
        importlib.import_module("torch._inductor")
    except Exception as e:  # pragma: no cover - broken installs
        return f"torch._inductor cannot be imported ({type(e).__name__}: {e})"
    if device.type == "cpu":
        try:
            from torch._inductor.cpp_builder import get_cpp_compiler
            get_cpp_compiler()
        except ImportError:  # pragma: no cover - other torch versions: let torch.compile tell
            pass
        except Exception as e:
            return f"Inductor needs a C++ compiler for CPU code (g++ or clang++ on the PATH, or $CXX): {e}"
    elif device.type == "cuda":
        try:
            from torch.utils._triton import has_triton
        except ImportError:  # pragma: no cover
            return None
        if not has_triton():
            cap = ""
            if torch.cuda.is_available():
                major, minor = torch.cuda.get_device_capability(device)
                cap = f"; this GPU has compute capability {major}.{minor}"
            return ("Inductor needs Triton (pip install triton) and a GPU of compute capability 7.0 or newer "
                    f"for CUDA code{cap}")
    return None


def check_inductor(device: torch.device | str, option: str, off: str) -> None:
    """Raise :class:`CompileUnavailable` naming ``option`` (e.g. ``trainer.compile=true``) and how to turn it
    off (``off``) when :func:`inductor_problem` finds one."""
    problem = inductor_problem(device)
    if problem:
        raise CompileUnavailable(f"{option}: torch.compile with Inductor is not available on this platform "
                                 f"(torch {torch.__version__}, device {torch.device(device)}): {problem}. "
                                 f"{off} to run the model uncompiled.")


def _capture_rnns() -> None:
    """TorchDynamo leaves ``nn.LSTM`` (HorizonNet's sequence model) out of the graph unless its ``allow_rnn``
    option is on (torch 2.14); the models' contract test compiles them whole with it."""
    import torch._dynamo.config as dynamo_config
    dynamo_config.allow_rnn = True


def compile_for_training(model: torch.nn.Module, device: torch.device) -> torch.nn.Module:
    """``torch.compile(model, dynamic=False)`` (Inductor, default mode) after :func:`check_inductor`; ``model`` is
    the module the training step calls (the DDP wrapper under DDP). Static shapes: a run trains at one size, and a
    model compiled before at another size would otherwise be recompiled with symbolic sizes."""
    check_inductor(device, "trainer.compile=true", "Set trainer.compile=false")
    _capture_rnns()
    return torch.compile(model, dynamic=False)


class FrozenInference(torch.nn.Module):
    """An eval-mode model compiled by Inductor with freezing: every call runs under ``torch.no_grad()`` with
    ``torch._inductor.config.freezing`` set (see :func:`compile_for_inference`). ``parameters()`` and
    ``state_dict()`` are the plain model's (under ``compiled._orig_mod``)."""

    def __init__(self, model: torch.nn.Module):
        super().__init__()
        _capture_rnns()
        self.compiled = torch.compile(model, dynamic=False)

    def forward(self, *args, **kwargs):
        import torch._inductor.config as inductor_config
        with torch.no_grad(), inductor_config.patch(freezing=True):
            return self.compiled(*args, **kwargs)


def compile_for_inference(model: torch.nn.Module, device: torch.device | str,
                          option: str = "--compile") -> FrozenInference:
    """``model`` (eval mode) compiled with ``torch.compile`` (Inductor) and freezing, after
    :func:`check_inductor`: the weights become constants of the graph (folded, convolution weights prepacked),
    so they must not change afterwards (the compiled code would not follow). Compiled lazily at the first call.

    Freezing is the global ``torch._inductor.config.freezing``, set around each call by
    :class:`FrozenInference`: TorchDynamo reads it when it traces (with gradients off) to keep the parameters
    as constants, and on torch 2.14 ``torch.compile(model, options={"freezing": True})`` does not reach that
    point (the parameters stay graph inputs and nothing is frozen)."""
    check_inductor(device, option, f"Leave out {option}")
    if model.training:
        raise ValueError(f"{option}: the model must be in eval mode to be compiled for inference")
    return FrozenInference(model)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class CompileTimer:
    """The compile time of a lazily compiled training step: the wall time of the first step that ran
    (tracing + Inductor compilation of forward and backward + the step itself) minus that of the second
    (a compiled step). Logged once after the second step, or by :meth:`finish` as an upper bound when the
    run had a single step. CUDA is synchronised around these two steps only."""

    def __init__(self, device: torch.device, enabled: bool = True):
        self.device = device
        self.enabled = enabled
        self.times: list[float] = []
        self._t0 = 0.0
        self.compile_s: float | None = None

    def start(self) -> None:
        if self.enabled:
            _sync(self.device)
            self._t0 = time.perf_counter()

    def stop(self, ran: bool) -> None:
        """After a step; ``ran``: the step was not skipped (a skipped batch does not count)."""
        if not self.enabled:
            return
        _sync(self.device)
        if ran:
            self.times.append(time.perf_counter() - self._t0)
        if len(self.times) >= 2:
            first, second = self.times[:2]
            self.compile_s = max(0.0, first - second)
            if self.compile_s < max(0.05, 0.5 * second):
                log.info("torch.compile: no compile time to report: the first training step (%.2f s) was not "
                         "slower than the second (%.2f s), so its graphs had already been compiled in this process "
                         "(torch.compile reuses them for a model of the same code and shapes)", first, second)
            else:
                log.info("compiled the model in %.1f s (torch.compile, Inductor: the first training step took "
                         "%.1f s with tracing and compiling forward and backward, the second %.2f s)",
                         self.compile_s, first, second)
            self.enabled = False

    def finish(self) -> None:
        """At the end of the run: with a single timed step, log it as an upper bound of the compile time."""
        if self.enabled and len(self.times) == 1:
            log.info("compiled the model in at most %.1f s (torch.compile, Inductor: the only training step, "
                     "compile included, took that long)", self.times[0])
            self.enabled = False
