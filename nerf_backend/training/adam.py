"""Adam (Kingma and Ba) over parameter groups: ``torch.optim.Adam``'s update (its fused kernel
where the device has one) and its ``state_dict`` layout, so checkpoints written by either load
into the other, without ``torch.optim``.

Why not ``torch.optim.Adam``: its base class imports ``torch._dynamo`` on first use, 0.9-2 s in
every process that trains, longer than a short training itself on a small scene (the test
suite starts a few hundred of them, the add-on one a training). The update is the same
kernel, ``torch._fused_adam_``, on the CPU, CUDA and MPS; a device without it takes the
textbook update written here, which the tests hold to torch's.

Example:
    >>> import torch
    >>> weight = torch.nn.Parameter(torch.zeros(2))
    >>> adam = Adam([{"params": [weight], "lr": 0.1}])
    >>> (weight - 1).square().sum().backward()
    >>> adam.step()
    >>> [round(value, 4) for value in weight.tolist()]  # Adam's first step moves each value by lr
    [0.1, 0.1]
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable

import torch
from torch import Tensor
from torch.autograd.graph import increment_version

# The settings a group carries besides its parameters.
GROUP_SETTINGS = ("lr", "initial_lr", "betas", "eps")
# torch's Adam's other settings, never changed by this project: not read from a checkpoint,
# written into one so that torch.optim.Adam loads it too.
TORCH_GROUP_DEFAULTS = {"weight_decay": 0.0, "amsgrad": False, "maximize": False, "foreach": None,
                        "capturable": False, "differentiable": False, "fused": None,
                        "decoupled_weight_decay": False}
# Device types whose PyTorch has no fused Adam (found on first use).
_unfused: set[str] = set()


class Adam:
    """Adam over ``groups`` (dicts with ``params`` and ``lr``, and any other settings the
    caller reads back, such as ``initial_lr``); ``param_groups``, ``state``, ``zero_grad``,
    ``step``, ``state_dict`` and ``load_state_dict`` as ``torch.optim.Adam`` has them (what
    ``torch.amp.GradScaler`` uses too)."""

    def __init__(self, groups: Iterable[dict], betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8) -> None:
        self.param_groups = [{"betas": tuple(betas), "eps": eps, **group, "params": list(group["params"])}
                             for group in groups]
        if not any(group["params"] for group in self.param_groups):
            raise ValueError("Adam was given no parameters")
        self.state: defaultdict[Tensor, dict] = defaultdict(dict)

    def zero_grad(self, set_to_none: bool = True) -> None:
        for group in self.param_groups:
            for parameter in group["params"]:
                if parameter.grad is None:
                    continue
                if set_to_none:
                    parameter.grad = None
                else:
                    parameter.grad.detach_().zero_()

    @torch.no_grad()
    def step(self, closure=None):
        """One update of every parameter that has a gradient; ``closure`` (re-evaluating the
        loss) as torch's optimisers take it."""
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            parameters = [p for p in group["params"] if p.grad is not None]
            buckets: dict[tuple, list[Tensor]] = defaultdict(list)
            for parameter in parameters:  # the fused kernel takes tensors of one device and type
                buckets[(parameter.device, parameter.dtype)].append(parameter)
            for bucket in buckets.values():
                self._update(group, bucket)
        return loss

    def _moments(self, parameter: Tensor) -> dict:
        state = self.state[parameter]
        if "exp_avg" not in state:
            # The step count a float on the parameter's device, as torch's fused Adam keeps it.
            state["step"] = torch.zeros((), dtype=torch.float32, device=parameter.device)
            state["exp_avg"] = torch.zeros_like(parameter, memory_format=torch.preserve_format)
            state["exp_avg_sq"] = torch.zeros_like(parameter, memory_format=torch.preserve_format)
        return state

    def _update(self, group: dict, parameters: list[Tensor]) -> None:
        states = [self._moments(p) for p in parameters]
        steps = [state["step"] for state in states]
        for step in steps:
            step += 1
        beta1, beta2 = group["betas"]
        lr, eps = float(group["lr"]), float(group["eps"])
        device = parameters[0].device.type
        if device not in _unfused:
            try:
                torch._fused_adam_(parameters, [p.grad for p in parameters], [s["exp_avg"] for s in states],
                                   [s["exp_avg_sq"] for s in states], [], steps, lr=lr, beta1=beta1, beta2=beta2,
                                   weight_decay=0.0, eps=eps, amsgrad=False, maximize=False)
                # The fused kernel leaves the parameters' version counters where they were (on the
                # CPU, torch 2.13): moved on here, as an in-place operation's would be, so that what
                # is kept of the old values (tensor_keys.kept_derived) is made again.
                for parameter in parameters:
                    increment_version(parameter)
                return
            except (RuntimeError, NotImplementedError, AttributeError):  # not built for this device
                _unfused.add(device)
        for parameter, state in zip(parameters, states):
            textbook_adam_update(parameter, parameter.grad, state["exp_avg"], state["exp_avg_sq"],
                                 float(state["step"]), lr, beta1, beta2, eps)

    def state_dict(self) -> dict:
        """torch.optim's layout: parameters numbered across the groups in order."""
        index = {id(p): i for i, p in enumerate(p for group in self.param_groups for p in group["params"])}
        groups = [{**TORCH_GROUP_DEFAULTS, **{key: group[key] for key in GROUP_SETTINGS if key in group},
                   "params": [index[id(p)] for p in group["params"]]} for group in self.param_groups]
        state = {index[id(p)]: dict(values) for p, values in self.state.items() if id(p) in index}
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, saved: dict) -> None:
        """A state from ``state_dict`` (this class's or torch's Adam's) for the same groups of
        parameters of the same shapes: the moments, step counts and group settings."""
        groups = saved["param_groups"]
        if [len(g["params"]) for g in groups] != [len(g["params"]) for g in self.param_groups]:
            raise ValueError("the saved optimiser state has other parameter groups than this model")
        self.state = defaultdict(dict)
        for group, saved_group in zip(self.param_groups, groups):
            group.update({key: saved_group[key] for key in GROUP_SETTINGS if key in saved_group})
            for parameter, number in zip(group["params"], saved_group["params"]):
                if number in saved["state"]:
                    self.state[parameter] = {key: _placed(key, value, parameter)
                                             for key, value in saved["state"][number].items()}


def _placed(key: str, value, parameter: Tensor):
    """A saved state value on the parameter's device: the step count a float32 scalar, the
    moments in the parameter's type."""
    if not isinstance(value, Tensor):
        return value
    if key == "step":
        return value.to(device=parameter.device, dtype=torch.float32)
    if value.is_floating_point() and key in ("exp_avg", "exp_avg_sq"):
        return value.to(device=parameter.device, dtype=parameter.dtype)
    return value.to(device=parameter.device)


def textbook_adam_update(parameter: Tensor, gradient: Tensor, exp_avg: Tensor, exp_avg_sq: Tensor, step: float,
                         lr: float, beta1: float, beta2: float, eps: float) -> None:
    """Adam's update of one tensor in place, ``step`` counting from 1 (Kingma and Ba,
    Algorithm 1, with ε added to the bias-corrected root as PyTorch adds it)."""
    exp_avg.lerp_(gradient, 1 - beta1)
    exp_avg_sq.mul_(beta2).addcmul_(gradient, gradient, value=1 - beta2)
    denominator = (exp_avg_sq.sqrt() / (1 - beta2 ** step) ** 0.5).add_(eps)
    parameter.addcdiv_(exp_avg, denominator, value=-lr / (1 - beta1 ** step))
