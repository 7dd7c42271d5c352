"""A stand-in accelerator for machines without one: DeviceAudit watches a CPU run and records
every operation that would fail if the model sat on a GPU.

Tensors count as "on the device" when they are the given modules' weights and buffers, come out of
an operation on device tensors, or are created with or moved to a device object the audit knows as
the device's (the one it was given, or `.device` read off a device tensor). `.cpu()` and `.to()` any
other device bring a tensor back to the host. Recorded, with where they happened:

* a device tensor and a host tensor with dimensions in one operation (host 0-d tensors are fine, as
  on CUDA; a host index into a device tensor is fine too);
* `.numpy()` or `np.asarray` of a device tensor;
* a CPU generator drawing straight onto the device.

On the CPU `.to(device)` and `.cpu()` may return their input itself; the audit then hands back a
copy (as a real transfer does), so moving a tensor never re-labels the one it came from.
"""
from __future__ import annotations

import traceback
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode
from torch.utils.weak import WeakIdKeyDictionary

_THIS = str(Path(__file__).resolve())
_TORCH = str(Path(torch.__file__).resolve().parent)
_LIKE = {"zeros_like", "ones_like", "empty_like", "full_like", "rand_like", "randn_like", "randint_like"}
_SHAPE_ONLY = {"expand_as", "view_as", "reshape_as"}     # the other tensor lends its shape, not its data
_TO_HOST = {"cpu", "numpy", "__array__", "tolist", "item"}


def _name(func) -> str:
    return getattr(func, "__name__", str(func))


def _tensors(tree, out: list | None = None) -> list[torch.Tensor]:
    """The tensors in nested lists, tuples and dicts (torch's pytree is several times slower)."""
    out = [] if out is None else out
    if isinstance(tree, torch.Tensor):
        out.append(tree)
    elif isinstance(tree, (list, tuple)):
        for x in tree:
            _tensors(x, out)
    elif isinstance(tree, dict):
        for x in tree.values():
            _tensors(x, out)
    return out


class DeviceAudit(TorchFunctionMode):
    def __init__(self, device: torch.device, modules=()):
        super().__init__()
        self._devices = [device]                 # held, so that their ids stay theirs
        self._device_ids = {id(device)}
        self._on = WeakIdKeyDictionary()
        self.problems: list[str] = []
        for m in modules:
            for t in list(m.parameters()) + list(m.buffers()):
                self._on[t] = True

    # ------------------------------------------------------------ bookkeeping
    def on_device(self, t) -> bool:
        return isinstance(t, torch.Tensor) and t in self._on

    def _mark(self, out) -> None:
        for t in _tensors(out):
            self._on[t] = True

    def _is_device(self, d) -> bool:
        return d is not None and id(d) in self._device_ids

    def _record(self, func, what: str) -> None:
        frames = [f for f in traceback.extract_stack()[:-2] if f.filename not in (_THIS,)
                  and not f.filename.startswith(_TORCH)]
        where = " <- ".join(f"{Path(f.filename).name}:{f.lineno}" for f in reversed(frames[-4:]))
        self.problems.append(f"{_name(func)}: {what} (at {where})")

    # ------------------------------------------------------------ the rules
    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = _name(func)
        if name == "__get__":               # attribute reads: .device, .grad, .data, .shape, ...
            out = func(*args, **kwargs)
            attr = getattr(getattr(func, "__self__", None), "__name__", None)
            if self.on_device(args[0]):
                if attr == "device":
                    self._devices.append(out)
                    self._device_ids.add(id(out))
                elif isinstance(out, torch.Tensor):
                    self._mark(out)
            return out
        if name in _TO_HOST:
            out = func(*args, **kwargs)
            if name in ("numpy", "__array__") and self.on_device(args[0]):
                self._record(func, "a device tensor read as a NumPy array; bring it to the host with .cpu() first")
            return out.clone() if out is args[0] and self.on_device(out) else out
        if name == "to":
            return self._to(func, args, kwargs)
        generator = kwargs.get("generator")
        inputs = _tensors((args, kwargs))
        if name in _SHAPE_ONLY:
            inputs = inputs[:1]
        device_in = [t for t in inputs if self.on_device(t)]
        if name in _LIKE or not inputs:      # factories: where `device=` says, else the input's place
            to_device = self._is_device(kwargs["device"]) if "device" in kwargs else bool(device_in)
            if to_device and generator is not None and generator.device.type == "cpu":
                self._record(func, "a CPU generator cannot draw on the device; draw on the CPU, then .to(device)")
            out = func(*args, **kwargs)
            if to_device:
                self._mark(out)
            return out
        if name == "copy_":                  # copies across devices are what copy_ is for
            return func(*args, **kwargs)
        if name in ("__getitem__", "__setitem__"):
            return self._index(func, args, kwargs)
        host = [t for t in inputs if not self.on_device(t) and t.dim() > 0]
        if device_in and host:
            shapes = ", ".join(str(tuple(t.shape)) for t in host[:3])
            self._record(func, f"device tensors mixed with host tensors of shape {shapes}")
        out = func(*args, **kwargs)
        if device_in:
            self._mark(out)
        return out

    def _index(self, func, args, kwargs):
        target, index, value = args[0], _tensors(args[1]), _tensors(args[2:3])
        if self.on_device(target):           # CUDA takes host indices; a host value must be a scalar
            bad = [t for t in value if not self.on_device(t) and t.dim() > 0]
        else:                                # a device 0-d index or value is read as a number
            bad = [t for t in index + value if self.on_device(t) and t.dim() > 0]
        if bad:
            where = "into a device tensor" if self.on_device(target) else "with a host tensor"
            self._record(func, f"indexing {where} mixes in tensors of shape {tuple(bad[0].shape)} from the other side")
        out = func(*args, **kwargs)
        if self.on_device(target):
            self._mark(out)
        return out

    def _to(self, func, args, kwargs):
        src = args[0]
        target = kwargs.get("device")
        for a in args[1:]:
            if isinstance(a, (torch.device, str, int)) and not isinstance(a, bool):
                target = a
            elif isinstance(a, torch.Tensor):
                target = a
        out = func(*args, **kwargs)
        if target is None:                   # a dtype change stays where it is
            if self.on_device(src):
                self._mark(out)
            return out
        to_device = self.on_device(target) if isinstance(target, torch.Tensor) else self._is_device(target)
        if to_device != self.on_device(src) and out is src:
            out = out.clone()
        if to_device:
            self._mark(out)
        return out
