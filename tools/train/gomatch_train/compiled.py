"""Optional `torch.compile` of the training step's hot functions (`--compile`).

On a CPU a training step is bound by PyTorch running one small elementwise kernel after another, not by its
matrix products; inductor fuses such chains (and the EdgeConv neighbour maxima, a gather per neighbour) into
single loops. The functions marked `@compilable` run eagerly until `enable()` is called; compiled, they give
the same results up to float rounding. Shapes are dynamic, so sets of any size share one compiled graph.
"""

import functools

import torch

_enabled = False


def enable() -> None:
    """Compile every `@compilable` function on its next call."""
    global _enabled
    _enabled = True


def disable() -> None:
    """Back to the eager functions (compiled graphs are kept for a later `enable()`)."""
    global _enabled
    _enabled = False


def compilable(fn):
    """`fn`, or its `torch.compile(dynamic=True)` version once `enable()` was called."""
    compiled = None

    @functools.wraps(fn)
    def dispatch(*args, **kwargs):
        nonlocal compiled
        if not _enabled or torch.compiler.is_compiling():  # eager, or inlined into a caller being compiled
            return fn(*args, **kwargs)
        if compiled is None:
            compiled = torch.compile(fn, dynamic=True)
        return compiled(*args, **kwargs)

    return dispatch
