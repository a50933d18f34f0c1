"""Reading pickles written by other tools without running their code: :func:`load_pickle`.

``pickle.load`` may call any importable function named in the file. :class:`RestrictedUnpickler` resolves
only what plain data needs (NumPy arrays, dtypes and scalars; dicts, lists, tuples, strings and numbers are
pickle opcodes and need no lookup) and refuses anything else with a one-line
:class:`s3k.base.errors.UserError` naming the file and the object it asked for. No array larger than the file
itself is allocated (its contents must come from the file), so a few bytes cannot ask for gigabytes.
"""

from __future__ import annotations

import io
import math
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from s3k.base.errors import UserError

_ALLOWED = {
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"),
    ("numpy._core.numeric", "_frombuffer"),
    ("collections", "OrderedDict"),
}


def _nbytes(shape: Any, dtype: Any) -> int | None:
    """Bytes of an array of ``shape`` and ``dtype``, None when they do not describe one."""
    try:
        dims = [int(shape)] if isinstance(shape, int) else [int(s) for s in shape]
        return math.prod(max(d, 0) for d in dims) * np.dtype(dtype).itemsize
    except (TypeError, ValueError, OverflowError):
        return None


class _Ndarray:
    """Stands for ``numpy.ndarray`` in a pickle: an array is allocated only up to the unpickler's budget."""

    def __init__(self, unpickler: RestrictedUnpickler) -> None:
        self.unpickler = unpickler

    def __call__(self, shape: Any, dtype: Any = float, *args: Any, **kwargs: Any) -> Any:
        self.unpickler.allocate(shape, dtype)
        return np.ndarray(shape, dtype, *args, **kwargs)


class RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that builds NumPy arrays and Python containers and nothing else, and allocates no array
    larger than ``budget`` bytes (an array's contents come from the file: a pickle asks for no more memory
    than its own size, unless it lies)."""

    def __init__(self, file: Any, source: str, budget: int = 1 << 30) -> None:
        super().__init__(file)
        self.source, self.budget = source, budget

    def allocate(self, shape: Any, dtype: Any) -> None:
        """Refuse an array of ``shape`` and ``dtype`` larger than the budget."""
        n = _nbytes(shape, dtype)
        if n is not None and n > self.budget:
            raise UserError(f"{self.source}: the pickle asks for an array of {n} bytes (shape {shape}); "
                            f"it holds at most {self.budget}")

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("numpy", "ndarray"):
            return _Ndarray(self)
        if name == "_reconstruct" and (module, name) in _ALLOWED:
            real = super().find_class(module, name)

            def reconstruct(subtype: Any, shape: Any, dtype: Any) -> Any:
                self.allocate(shape, dtype)
                if isinstance(subtype, _Ndarray):
                    subtype = np.ndarray
                return real(subtype, shape, dtype)

            return reconstruct
        if (module, name) in _ALLOWED:
            return super().find_class(module, name)
        raise UserError(
            f"{self.source}: the pickle asks for {module}.{name}; s3k reads only NumPy arrays, dicts, lists "
            "and numbers from pickles (other objects could run code)"
        )


def load_pickle(path: str | Path) -> Any:
    """The content of the pickle ``path``, loaded with :class:`RestrictedUnpickler`.

    Raises:
        FileNotFoundError: no such file. UserError: a truncated or non-pickle file, or one holding other
            objects, naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    # read whole: a length in the file then cannot make the reader allocate more than the file holds
    data = path.read_bytes()
    try:
        return RestrictedUnpickler(io.BytesIO(data), str(path), budget=len(data)).load()
    except UserError:
        raise
    except Exception as exc:  # UnpicklingError, EOFError, ValueError... on a corrupt file
        raise UserError(f"{path}: not a readable pickle ({type(exc).__name__}: {exc})") from None
