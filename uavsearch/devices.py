"""Where tensors live: one function picks the device (Stable-Baselines3's `get_device` convention), and the
helpers every module uses to put its tensors, generators and checkpoints there.

- `resolve_device("auto" | "cpu" | "cuda" | "cuda:N")`: auto is CUDA when torch sees one, else the CPU; asking
  for CUDA where there is none is a one-line user error.
- `make_generator(seed, device)`: a seeded `torch.Generator` on that device (a sampler's generator must live
  where its tensors do; a CPU generator stays the one `torch.Generator().manual_seed(seed)` gives).
- `to_device(x, device)`: a tensor, or every tensor field of a NamedTuple (a view cache, cell tables), moved;
  `follow(obj, device)`: a plain object's tensor attributes moved (a rule policy built from a config follows
  the inputs it is asked about); `device_of(x)`: where a tensor, a module or a view source lives.
- `cpu_state(module)`: a state dict on the CPU, what checkpoints save so they load anywhere.
- `DeviceArgs`: the `--device` flag every training and evaluation command shares (parallel.ScaleOutArgs).

The module imports torch only inside its functions: the commands that read `DeviceArgs` without ever building a
tensor (`uavsearch --help`, scene and flight commands) do not pay torch's start-up. On the CPU everything here is
the identity, so CPU results are the same bits whichever device code path ran.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from .cli_args import opt
from .errors import UavsearchError

if TYPE_CHECKING:
    import torch

DEVICES = ("auto", "cpu", "cuda")


@dataclass
class DeviceArgs:
    """The device flag of every training and evaluation command."""
    device: str = opt("auto", "where tensors live: auto (CUDA when available, else CPU), cpu, cuda or cuda:N")


def cuda_available() -> bool:
    import torch

    return bool(torch.cuda.is_available())


def resolve_device(device: Any = "auto") -> "torch.device":
    """"auto" | "cpu" | "cuda" | "cuda:N" | a torch.device -> the torch.device to use (SB3's get_device)."""
    import torch

    if isinstance(device, torch.device):
        name = str(device)
    else:
        name = str(device if device is not None else "auto").strip().lower()
    if name == "auto":
        name = "cuda" if cuda_available() else "cpu"
    kind, _, index = name.partition(":")
    if kind not in ("cpu", "cuda") or (index and not index.isdecimal()) or (kind == "cpu" and index):
        raise UavsearchError(f"unknown device {device!r}; valid: auto, cpu, cuda, cuda:N")
    if kind == "cuda":
        if not cuda_available():
            raise UavsearchError(f"device {name}: this torch ({torch.__version__}) sees no CUDA GPU "
                                 "(install a CUDA build of torch: docs/learning.md; or use --device cpu)")
        if index and int(index) >= torch.cuda.device_count():
            raise UavsearchError(f"device {name}: only {torch.cuda.device_count()} CUDA device(s) here")
    return torch.device(name)


def make_generator(seed: int, device: Any = "cpu") -> "torch.Generator":
    """A torch.Generator on `device` (resolved), seeded; on the CPU the same stream as torch.Generator()."""
    import torch

    return torch.Generator(device=resolve_device(device)).manual_seed(int(seed))


def to_device(x, device: Any):
    """`x` on `device`: a tensor moved (itself when it is there already), every tensor field of a NamedTuple
    moved (the others kept), None kept."""
    import torch

    if x is None:
        return None
    dev = resolve_device(device)
    if isinstance(x, torch.Tensor):
        return x.to(dev)
    if isinstance(x, tuple) and hasattr(x, "_replace"):
        return x._replace(**{k: v.to(dev) for k, v in x._asdict().items() if isinstance(v, torch.Tensor)})
    raise TypeError(f"to_device: a tensor or a NamedTuple of tensors, not {type(x).__name__}")


def follow(obj, device):
    """Move the tensor attributes of a plain object (a rule policy's footprints, a route table) to `device` where
    they are not there yet, and return it: an object built from a config follows the inputs it is asked about."""
    import torch

    for k, v in list(vars(obj).items()):
        if isinstance(v, torch.Tensor):
            setattr(obj, k, v.to(device))  # itself where it is there already
    return obj


def device_of(x, default: Any = "cpu") -> "torch.device":
    """The device of a tensor, of a module's first parameter or buffer, or of an object's `device` attribute."""
    import torch

    if isinstance(x, torch.Tensor):
        return x.device
    if isinstance(x, torch.nn.Module):
        for t in (*x.parameters(), *x.buffers()):
            return t.device
    dev = getattr(x, "device", None)
    return torch.device(dev) if dev is not None else torch.device(default)


def cpu_state(module) -> dict:
    """A module's state dict (or a state dict) detached and on the CPU: what a checkpoint stores."""
    sd = module.state_dict() if hasattr(module, "state_dict") else module
    return {k: v.detach().cpu() for k, v in sd.items()}


__all__ = ["DEVICES", "DeviceArgs", "cpu_state", "cuda_available", "device_of", "follow", "make_generator",
           "resolve_device", "to_device"]
