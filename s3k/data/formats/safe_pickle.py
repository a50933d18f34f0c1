"""Reading pickles written by other tools without running their code: :func:`load_pickle`.

``pickle.load`` may call any importable function named in the file. :class:`RestrictedUnpickler` resolves
only what plain data needs (NumPy arrays, dtypes and scalars; dicts, lists, tuples, strings and numbers are
pickle opcodes and need no lookup) and refuses anything else with a one-line :class:`s3k.errors.UserError`
naming the file and the object it asked for.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

from s3k.errors import UserError

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


class RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that builds NumPy arrays and Python containers and nothing else."""

    def __init__(self, file: Any, source: str) -> None:
        super().__init__(file)
        self.source = source

    def find_class(self, module: str, name: str) -> Any:
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
    with path.open("rb") as f:
        try:
            return RestrictedUnpickler(f, str(path)).load()
        except UserError:
            raise
        except Exception as exc:  # UnpicklingError, EOFError, ValueError... on a corrupt file
            raise UserError(f"{path}: not a readable pickle ({type(exc).__name__}: {exc})") from None
