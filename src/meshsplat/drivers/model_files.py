"""Reading SMPL / SMPL-X / FLAME model files (the user's own licensed files) into plain numpy arrays.

``.npz`` files load with ``allow_pickle=False``. ``.pkl`` files go through a restricted unpickler
that builds only numpy arrays, scipy sparse matrices and plain containers; objects of ``chumpy``
(which the official pickles use and which breaks on numpy >= 1.24) are read without importing
chumpy: a leaf ``Ch`` keeps its array in its state under ``x``.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from meshsplat.errors import MeshsplatError

__all__ = ["read_model_file"]

_NUMPY_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy.core.numeric", "_frombuffer"),
    ("numpy._core.numeric", "_frombuffer"),
    ("copyreg", "_reconstructor"),
    ("builtins", "object"),
    ("__builtin__", "object"),
    ("copy_reg", "_reconstructor"),
    ("_codecs", "encode"),
}


class _Captured:
    """Stand-in for a chumpy or scipy.sparse object: keeps the constructor args and the pickled state."""

    module = ""
    name = ""

    def __init__(self, *args, **kwargs):
        self.args, self.state = args, None

    def __setstate__(self, state):
        self.state = state


def _captured_class(module: str, name: str) -> type:
    return type(f"Captured_{name}", (_Captured,), {"module": module, "name": name})


class _ModelUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if (module, name) in _NUMPY_GLOBALS:
            return super().find_class(module, name)
        if module.split(".")[0] == "chumpy" or module.startswith("scipy.sparse"):
            return _captured_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")


def _state_dict(obj: _Captured) -> dict:
    st = obj.state
    if isinstance(st, tuple) and len(st) == 2 and isinstance(st[1], dict):  # (dict, slots)
        st = {**(st[0] or {}), **st[1]}
    return st if isinstance(st, dict) else {}


def _to_array(value, path: Path, key: str):
    if isinstance(value, _Captured):
        st = _state_dict(value)
        if value.module.startswith("scipy.sparse"):
            from scipy import sparse

            shape = st.get("_shape", st.get("shape"))
            if not all(k in st for k in ("data", "indices", "indptr")) or shape is None:
                raise MeshsplatError(f"{path}: cannot read the sparse matrix {key!r}; convert the file to plain numpy")
            cls = sparse.csr_matrix if "csr" in value.name else sparse.csc_matrix
            return cls((st["data"], st["indices"], st["indptr"]), shape=tuple(shape)).toarray()
        if isinstance(st.get("x"), np.ndarray):
            return np.asarray(st["x"])
        raise MeshsplatError(
            f"{path}: key {key!r} is a derived chumpy expression; install chumpy or convert the file "
            "to plain numpy arrays"
        )
    if hasattr(value, "toarray"):
        return value.toarray()
    return value


def read_model_file(path: Path) -> dict:
    """All top-level entries of a model file; arrays as numpy (sparse densified, chumpy unwrapped)."""
    path = Path(path)
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                out = {}
                for k in z.files:
                    try:
                        out[k] = z[k]
                    except ValueError:  # object arrays (e.g. joint2num) are not needed
                        continue
                return out
        with open(path, "rb") as fh:
            data = _ModelUnpickler(fh, encoding="latin1").load()
    except MeshsplatError:
        raise
    except Exception as e:  # noqa: BLE001 - any unreadable file becomes one line
        raise MeshsplatError(f"{path}: cannot read the model file ({type(e).__name__}: {e})") from None
    if not isinstance(data, dict):
        raise MeshsplatError(f"{path}: expected a pickled dict of arrays, got {type(data).__name__}")
    return {k: _to_array(v, path, k) for k, v in data.items()}
