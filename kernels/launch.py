"""Kernel launches whose Python-side cost is paid once: recorded launch commands, reused call after call.

``wp.launch`` converts every argument to its C form on every call (18 us of host time for the rasterizer's
fifteen-argument compositing kernel on this project's 2-core development machine, 2 us reused). On the host-bound
hot paths (an eager rasterizer pass launches four kernels and calls Warp's sort and scan three times, and a pass at
avatar scale takes less GPU time than the host needs to queue it), that packing is a large share of the host's work.
:func:`launch` records one ``warp.Launch`` command per kernel, device, block size and direction the first time, and
later only copies the new arguments into the command's own parameter block (an array argument is a 56-byte
descriptor copied in place; a scalar is written only when it changed) before launching it: 2 us for the compositing
kernel.

What it does not do that ``wp.launch`` does: record onto a ``wp.Tape``, launch under a Warp API capture (APIC) or in
Warp's deterministic mode (generic kernels, whose overload depends on the arguments, go through ``wp.launch``). A
command holds no reference to the arguments of its last call (their descriptors are copied, not kept), so a launch
never keeps a buffer alive longer than ``wp.launch`` would; as with ``wp.launch``, the caller keeps its buffers
alive until the kernel has been queued, and stream order does the rest.

Commands are kept per thread (a command's parameter block is rewritten by every call).
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Sequence

import warp as wp

__all__ = ["REUSE_COMMANDS", "launch", "reused_commands"]

REUSE_COMMANDS = True
"""False: :func:`launch` calls ``wp.launch`` every time (for comparisons of the host's work, and debugging)."""

_LOCAL = threading.local()


def reused_commands() -> dict:
    """This thread's recorded commands, keyed by (kernel, device name, block size, adjoint) (for tests)."""
    commands = getattr(_LOCAL, "commands", None)
    if commands is None:
        commands = _LOCAL.commands = {}
    return commands


def _descriptor_of(value):
    """The C descriptor of an array argument (a ``warp.array`` or a descriptor already), or None for anything
    else."""
    if isinstance(value, ctypes.Structure):
        return value
    if isinstance(value, wp.array):
        return value.__ctype__()
    return None


class _Command:
    """One recorded launch and the parameter slots later calls write into."""

    __slots__ = ("launch", "dim", "array_slots", "scalar_slots", "scalars")

    def __init__(self, kernel, device, dim, values: Sequence, adjoint_values: Sequence, *, block_dim, adjoint):
        argument_count = len(kernel.adj.args)
        command = wp.launch(kernel, dim=dim, inputs=list(values), adj_inputs=list(adjoint_values), device=device,
                            block_dim=block_dim, adjoint=adjoint, record_cmd=True)
        if not isinstance(command, wp.Launch):
            raise TypeError(f"kernel {kernel.key} cannot be recorded as a reusable launch")
        command.fwd_args = None  # would keep the first call's arguments alive
        command.adj_args = None
        self.launch = command
        self.dim = dim
        self.array_slots = []  # (position in the call's values, address of the command's own descriptor, size)
        self.scalar_slots = []  # (position, parameter index, is_adjoint)
        self.scalars = []
        for position, value in enumerate(list(values) + list(adjoint_values)):
            is_adjoint = position >= argument_count
            index = position - argument_count if is_adjoint else position
            if wp.types.is_array(kernel.adj.args[index].type):
                # The command's own descriptor, holding no reference (None: Warp's null array, all zeros).
                own = type(command.params[1 + position]).from_buffer_copy(command.params[1 + position])
                command.set_param_at_index_from_ctype(index, own, adjoint=is_adjoint)
                self.array_slots.append((position, ctypes.addressof(own), ctypes.sizeof(own)))
            else:
                self.scalar_slots.append((position, index, is_adjoint))
                self.scalars.append(value)

    def run(self, dim, values: Sequence) -> None:
        command = self.launch
        if dim != self.dim:
            command.set_dim(dim)
            self.dim = dim
        memmove = ctypes.memmove
        for position, address, size in self.array_slots:
            value = values[position]
            if value is None:  # an optional array left out: Warp's null array
                ctypes.memset(address, 0, size)
                continue
            descriptor = _descriptor_of(value)
            if descriptor is None:
                raise TypeError(f"argument {position} of {command.kernel.key} must be an array or None, got "
                                f"{type(value).__name__}")
            memmove(address, ctypes.addressof(descriptor), size)
        scalars = self.scalars
        for slot, (position, index, is_adjoint) in enumerate(self.scalar_slots):
            value = values[position]
            previous = scalars[slot]
            if value is previous or (type(value) is type(previous) and isinstance(value, (int, float))
                                     and value == previous):
                continue
            if isinstance(value, (int, float)):  # written in place: the parameter keeps its address
                command.set_param_at_index_from_ctype(index, value, adjoint=is_adjoint)
            else:  # vectors, matrices, structs: converted as wp.launch would
                command.set_param_at_index(index, value, adjoint=is_adjoint)
            scalars[slot] = value
        command.launch()


def _size(dim) -> int:
    if isinstance(dim, int):
        return dim
    size = 1
    for extent in dim:
        size *= extent
    return size


def launch(kernel, *, dim, inputs: Sequence = (), outputs: Sequence = (), adj_inputs: Sequence = (),
           adj_outputs: Sequence = (), adjoint: bool = False, block_dim: int | None = None, device=None) -> None:
    """Launch ``kernel`` like ``wp.launch``, reusing a recorded command (see the module doc).

    Args:
        kernel: a ``@wp.kernel`` whose arguments all have concrete types.
        dim: launch dimensions (an int or a tuple); nothing runs when they hold no thread.
        inputs, outputs: the kernel's arguments in order: ``warp.array`` objects, array descriptors (e.g.
            :func:`warpavatar._src.warp_utils.warp_descriptor`), None for an optional array, or scalars.
        adj_inputs, adj_outputs: with ``adjoint=True``, the adjoint arguments, as ``wp.launch`` takes them (one
            per kernel argument in all; ``None`` for an array without a gradient).
        adjoint: run the kernel's adjoint.
        block_dim: threads per block (as ``wp.launch``).
        device: the Warp device; by default Warp's current device (the stream is that device's current one).

    Raises:
        TypeError: an array argument of the kernel got something else than an array or None.
    """
    if _size(dim) == 0:
        return
    if kernel.is_generic or not REUSE_COMMANDS:  # a generic kernel's overload depends on the arguments' types
        wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, adj_inputs=adj_inputs, adj_outputs=adj_outputs,
                  adjoint=adjoint, block_dim=block_dim, device=device)
        return
    device = wp.get_device(device)
    values = list(inputs)
    values.extend(outputs)
    adjoint_values = list(adj_inputs)
    adjoint_values.extend(adj_outputs)
    key = (kernel, device.alias, block_dim, adjoint)
    commands = reused_commands()
    command = commands.get(key)
    if command is None:
        command = commands[key] = _Command(kernel, device, dim, values, adjoint_values, block_dim=block_dim,
                                           adjoint=adjoint)
        command.launch.launch()
        return
    values.extend(adjoint_values)
    command.run(dim, values)
