"""Optimizers of the fit: Adam as one fused kernel per parameter group, without ``torch.optim``'s machinery.

``torch.optim.Optimizer`` imports ``torch._dynamo`` (and with it sympy and much of torch.distributed) the first time
a parameter group is added, a step taken or a state saved, to keep those methods out of ``torch.compile``'s tracing.
Nothing here is compiled, and the import is a large part of a fit's set-up: without it the trainer's construction
takes 0.8-1.6 s less on this project's 2-core development machine, and on the H100 machines that check the fit's time,
whose torch install has no cached bytecode, it took 0.86 s against 5.29 s with torch's Adam (two machines of session
25). :class:`Optimizer` keeps the API the fit uses (``param_groups``, ``state``, ``step``, ``zero_grad``,
``state_dict``, ``load_state_dict``, ``add_param_group``) and torch's state-dict layout, so checkpoints written with
``torch.optim.Adam`` load into :class:`Adam` and back.

:class:`Adam`'s step is torch's fused Adam kernel (``torch._fused_adam_``, on CPU and CUDA alike), called as
``torch.optim.Adam(fused=True)`` calls it: the same results, bit for bit (the tests compare them). Its step counts
are float32 tensors on the parameters' device, and a learning rate may be a 0-dim tensor there, changed in place,
so a step can be captured in a CUDA graph and replayed.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable

import torch

__all__ = ["Optimizer", "Adam"]


class Optimizer:
    """Parameter groups and per-parameter state, as ``torch.optim.Optimizer`` keeps them (see the module doc).

    Args:
        params: tensors, or dicts each with ``"params"`` (tensors) and options that override ``defaults`` (any
            other key, e.g. ``"name"``, is kept in the group).
        defaults: the options of a group that does not set them.

    Raises:
        ValueError: no parameters, a parameter in two groups, a tensor that is not a leaf.
    """

    def __init__(self, params, defaults: dict):
        self.defaults = dict(defaults)
        self.state: defaultdict[torch.Tensor, dict] = defaultdict(dict)
        self.param_groups: list[dict] = []
        groups = list(params)
        if not groups:
            raise ValueError("the optimizer got no parameters")
        if not isinstance(groups[0], dict):
            groups = [{"params": groups}]
        for group in groups:
            self.add_param_group(group)

    def add_param_group(self, param_group: dict) -> None:
        """Add a group: ``param_group["params"]`` (a tensor or an iterable of them) with its options."""
        params = param_group["params"]
        params = [params] if isinstance(params, torch.Tensor) else list(params)
        seen = {id(parameter) for group in self.param_groups for parameter in group["params"]}
        for parameter in params:
            if not isinstance(parameter, torch.Tensor) or not parameter.is_leaf:
                raise ValueError(f"the optimizer can only optimize leaf tensors, got {type(parameter).__name__}")
            if id(parameter) in seen:
                raise ValueError("a parameter appears in more than one group")
            seen.add(id(parameter))
        group = {**self.defaults, **param_group, "params": params}
        self.param_groups.append(group)

    def zero_grad(self, set_to_none: bool = True) -> None:
        """Drop every gradient (``set_to_none``) or zero it in place (its tensor kept: a captured step reads it)."""
        grads = []
        for group in self.param_groups:
            for parameter in group["params"]:
                if parameter.grad is None:
                    continue
                if set_to_none:
                    parameter.grad = None
                else:
                    if parameter.grad.grad_fn is not None:
                        parameter.grad.detach_()
                    else:
                        parameter.grad.requires_grad_(False)
                    grads.append(parameter.grad)
        for (same_kind,) in _columns_by_kind((grad,) for grad in grads).values():
            torch._foreach_zero_(same_kind)

    def state_dict(self) -> dict:
        """``{"state": {index: state}, "param_groups": [options with "params": [index, ...]]}``, parameters
        numbered in group order (torch's layout; the state's tensors are the optimizer's own, not copies)."""
        index: dict[int, int] = {}
        groups = []
        for group in self.param_groups:
            packed = {key: value for key, value in group.items() if key != "params"}
            packed["params"] = [index.setdefault(id(parameter), len(index)) for parameter in group["params"]]
            groups.append(packed)
        state = {index[id(parameter)]: dict(values) for parameter, values in self.state.items()
                 if id(parameter) in index}
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, state_dict: dict) -> None:
        """Take the state and the groups' options of ``state_dict`` (from :meth:`state_dict`, or from a
        ``torch.optim`` optimizer of the same groups); state tensors are copied onto each parameter's device
        (floating moments in its dtype).

        Raises:
            ValueError: the groups or their sizes differ from this optimizer's.
        """
        saved_groups = state_dict["param_groups"]
        if len(saved_groups) != len(self.param_groups) or any(
                len(saved["params"]) != len(own["params"]) for saved, own in zip(saved_groups, self.param_groups)):
            raise ValueError("the saved optimizer state has other parameter groups than this optimizer")
        parameters = {index: parameter for saved, own in zip(saved_groups, self.param_groups)
                      for index, parameter in zip(saved["params"], own["params"])}
        state: defaultdict[torch.Tensor, dict] = defaultdict(dict)
        for index, values in state_dict["state"].items():
            parameter = parameters[index]
            state[parameter] = {key: self._loaded_value(key, value, parameter) for key, value in values.items()}
        self.state = state
        self.param_groups = [{**saved, "params": own["params"]} for saved, own in zip(saved_groups, self.param_groups)]

    @staticmethod
    def _loaded_value(key: str, value, parameter: torch.Tensor):
        """A saved state value as this optimizer keeps it (tensors copied to the parameter's device; floating
        moments in its dtype, step counts in theirs)."""
        if not isinstance(value, torch.Tensor):
            return value
        if key == "step" or not value.is_floating_point():
            return value.to(device=parameter.device, copy=True)
        return value.to(device=parameter.device, dtype=parameter.dtype, copy=True)

    def step(self, closure=None):  # pragma: no cover (every optimizer defines its own)
        raise NotImplementedError


def _columns_by_kind(rows: Iterable[tuple[torch.Tensor, ...]]) -> dict[tuple, list[list[torch.Tensor]]]:
    """Rows of tensors grouped by the (device, dtype) of each row's first tensor, as columns: the per-operand lists
    that torch's multi-tensor kernels take, each of one device and dtype."""
    grouped: dict[tuple, list[list[torch.Tensor]]] = {}
    for row in rows:
        columns = grouped.setdefault((row[0].device, row[0].dtype), [[] for _ in row])
        for column, tensor in zip(columns, row):
            column.append(tensor)
    return grouped


_TORCH_ADAM_OPTIONS = {"amsgrad": False, "maximize": False, "foreach": None, "capturable": False,
                       "differentiable": False, "fused": True, "decoupled_weight_decay": False}
"""The options of ``torch.optim.Adam`` that :class:`Adam`'s step amounts to (written into its state dicts)."""


class Adam(Optimizer):
    """Adam (Kingma and Ba), one fused kernel launch per parameter group and device: ``torch.optim.Adam(...,
    fused=True)``'s results without its imports (see the module doc).

    Args:
        params: parameters or parameter groups (:class:`Optimizer`).
        lr: learning rate, a number or a 0-dim tensor on the parameters' device (read when a step runs: a
            captured step reads the value it holds then).
        betas: decay rates of the first and second moments, in [0, 1).
        eps: added to the square root of the second moment (>= 0).
        weight_decay: L2 penalty added to the gradient (>= 0).

    Attributes:
        found_inf: None, or a 0-dim float32 tensor on the parameters' device: where it holds a non-zero value when
            a step runs, the kernel leaves the parameters and moments as they are
            as torch's fused Adam does with a gradient scaler's flag (nor does the step count).

    Raises:
        ValueError: a negative learning rate, eps or weight decay, a beta outside [0, 1).
    """

    def __init__(self, params, *, lr: float | torch.Tensor = 1e-3, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8, weight_decay: float = 0.0):
        if isinstance(lr, torch.Tensor) and lr.numel() != 1:
            raise ValueError(f"a tensor learning rate must hold one value, got shape {list(lr.shape)}")
        if not float(lr) >= 0.0:
            raise ValueError(f"lr must be >= 0, got {float(lr)}")
        if not eps >= 0.0:
            raise ValueError(f"eps must be >= 0, got {eps}")
        if not all(0.0 <= beta < 1.0 for beta in betas):
            raise ValueError(f"betas must lie in [0, 1), got {tuple(betas)}")
        if not weight_decay >= 0.0:
            raise ValueError(f"weight_decay must be >= 0, got {weight_decay}")
        super().__init__(params, dict(lr=lr, betas=tuple(betas), eps=eps, weight_decay=weight_decay))
        self.found_inf: torch.Tensor | None = None

    def state_dict(self) -> dict:
        """:meth:`Optimizer.state_dict`, each group also naming the options ``torch.optim.Adam`` records (fused, no
        amsgrad, ...), so that torch's Adam loading it goes on with the same kernel."""
        saved = super().state_dict()
        for group in saved["param_groups"]:
            for key, value in _TORCH_ADAM_OPTIONS.items():
                group.setdefault(key, value)
        return saved

    @staticmethod
    def _loaded_value(key: str, value, parameter: torch.Tensor):
        if key == "step":  # float32 on the parameter's device, whatever wrote it (a number, a CPU count)
            return torch.as_tensor(value, dtype=torch.float32).to(device=parameter.device, copy=True)
        return Optimizer._loaded_value(key, value, parameter)

    @torch.no_grad()
    def step(self, closure=None):
        """One Adam step of every parameter with a gradient (``closure``, if given, is called first with
        gradients on and its loss returned).

        Raises:
            RuntimeError: a sparse gradient.
        """
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            rows = []  # (parameter, gradient, first moment, second moment, step count)
            for parameter in group["params"]:
                if parameter.grad is None:
                    continue
                if parameter.grad.is_sparse:
                    raise RuntimeError("Adam does not take sparse gradients")
                state = self.state[parameter]
                if not state:
                    state["step"] = torch.zeros((), dtype=torch.float32, device=parameter.device)
                    state["exp_avg"] = torch.zeros_like(parameter, memory_format=torch.preserve_format)
                    state["exp_avg_sq"] = torch.zeros_like(parameter, memory_format=torch.preserve_format)
                rows.append((parameter, parameter.grad, state["exp_avg"], state["exp_avg_sq"], state["step"]))
            beta1, beta2 = group["betas"]
            for (device, _), (params, grads, exp_avgs, exp_avg_sqs, steps) in _columns_by_kind(rows).items():
                lr = group["lr"]
                if isinstance(lr, torch.Tensor) and lr.device != device:
                    lr = float(lr) if lr.device.type == "cpu" else lr.to(device)
                found_inf = None if self.found_inf is None else self.found_inf.to(device)
                torch._foreach_add_(steps, 1)
                torch._fused_adam_(params, grads, exp_avgs, exp_avg_sqs, [], steps, amsgrad=False, lr=lr, beta1=beta1,
                                   beta2=beta2, weight_decay=group["weight_decay"], eps=group["eps"], maximize=False,
                                   grad_scale=None, found_inf=found_inf)
                if found_inf is not None:  # a skipped step does not count
                    torch._foreach_sub_(steps, [found_inf] * len(steps))
        return loss
