"""The UNet's weights on disk: named arrays in PyTorch's state-dict layout (enc1.0.weight,
enc1.1.running_mean, up2.weight, ...), so that names and shapes stay those of every model this
project has trained.

  .npz  what train.py writes beside its ONNX file and reads with --init (numpy only).
  .pt   a PyTorch state dict from the earlier trainer (a lab's checkpoint), read without PyTorch:
        the zip's pickle is unpickled with only the few classes a state dict of tensors uses.
"""
import collections
import os
import pickle
import zipfile

import numpy as np

_STORAGE_DTYPES = {
    "FloatStorage": np.float32, "DoubleStorage": np.float64, "HalfStorage": np.float16,
    "LongStorage": np.int64, "IntStorage": np.int32, "BoolStorage": np.bool_,
}


def save(path, arrays):
    np.savez(path, **{name: np.asarray(value) for name, value in arrays.items()})


def load(path):
    """{name: array} from a .npz or a PyTorch .pt state dict; exits naming the file otherwise."""
    if not os.path.isfile(path):
        raise SystemExit(f"{path}: no such file")
    try:
        if path.endswith(".npz"):
            with np.load(path) as f:
                return {name: f[name] for name in f.files}
        if path.endswith(".pt"):
            return _load_torch_state_dict(path)
    except (OSError, ValueError, KeyError, pickle.UnpicklingError, zipfile.BadZipFile) as e:
        raise SystemExit(f"{path}: not a readable weights file ({e})")
    raise SystemExit(f"{path}: unknown weights format (want .npz, or a PyTorch state dict .pt)")


class _StateDictUnpickler(pickle.Unpickler):
    """Rebuilds a torch.save()d state dict as numpy arrays; any other class is refused, so a
    checkpoint cannot run code on load."""

    def __init__(self, archive, prefix):
        super().__init__(archive.open(f"{prefix}data.pkl"))
        self.archive, self.prefix = archive, prefix
        # torch.save writes the byte order it stored the tensors in (older files: little-endian).
        order = f"{prefix}byteorder"
        self.order = "<" if order not in archive.namelist() or archive.read(order) == b"little" else ">"

    def find_class(self, module, name):
        if (module, name) == ("collections", "OrderedDict"):
            return collections.OrderedDict
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return _rebuild_tensor
        if module == "torch" and name in _STORAGE_DTYPES:
            return _STORAGE_DTYPES[name]
        raise pickle.UnpicklingError(f"{module}.{name} is not part of a state dict of tensors")

    def persistent_load(self, pid):
        kind, dtype, key, _location, numel = pid
        if kind != "storage":
            raise pickle.UnpicklingError(f"unexpected persistent id {kind!r}")
        data = self.archive.read(f"{self.prefix}data/{key}")
        return np.frombuffer(data, dtype=np.dtype(dtype).newbyteorder(self.order), count=numel)


def _rebuild_tensor(storage, offset, size, stride, *_):
    item = storage.itemsize
    view = np.lib.stride_tricks.as_strided(storage[offset:], shape=tuple(size),
                                           strides=tuple(s * item for s in stride))
    return view.astype(view.dtype.newbyteorder("="))


def _load_torch_state_dict(path):
    with zipfile.ZipFile(path) as archive:
        pickles = [name for name in archive.namelist() if name.endswith("/data.pkl")]
        if len(pickles) != 1:
            raise ValueError("no data.pkl in the archive (a torch.save() zip)")
        prefix = pickles[0][: -len("data.pkl")]
        state = _StateDictUnpickler(archive, prefix).load()
    if not isinstance(state, dict):
        raise ValueError("not a state dict")
    return {name: np.asarray(value) for name, value in state.items()}
