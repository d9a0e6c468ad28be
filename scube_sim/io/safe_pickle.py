"""Read pickles we did not write (dataset info files) without running their code.

Only plain containers and numpy arrays can be rebuilt; any other class in the stream is refused
with an error naming the file and the class.
"""

from __future__ import annotations

import pickle
from pathlib import Path

from ..errors import InputError

_ALLOWED = {
    ("builtins", name) for name in ("dict", "list", "tuple", "set", "frozenset", "complex", "bytearray", "slice",
                                    "range", "bool", "int", "float", "str", "bytes")
} | {
    ("collections", "OrderedDict"),
    ("_codecs", "encode"),  # protocol-2 pickles of numpy buffers spell bytes this way
    ("numpy", "ndarray"), ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"), ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
}


class UnsafePickleError(InputError):
    pass


class _Restricted(pickle.Unpickler):
    def __init__(self, fh, source: str):
        super().__init__(fh)
        self._source = source

    def find_class(self, module: str, name: str):
        if (module, name) in _ALLOWED or (module == "numpy" and name.endswith("DType")):
            return super().find_class(module, name)
        raise UnsafePickleError(f"{self._source}: refusing to load class {module}.{name} from a pickle "
                                f"(only builtins and numpy arrays are allowed)")


def load_pickle(path: str | Path):
    """Unpickle `path` allowing only builtins containers, scalars and numpy arrays/dtypes."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    with open(path, "rb") as fh:
        try:
            return _Restricted(fh, str(path)).load()
        except UnsafePickleError:
            raise
        except Exception as exc:
            raise InputError(f"{path}: not a readable pickle ({type(exc).__name__}: {exc})") from None
