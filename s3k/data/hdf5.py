"""Opening HDF5 files written by other tools (SLEAP analysis files and projects, NWB) so that they read only
what they hold themselves: :func:`open_hdf5`, :func:`check_self_contained`.

HDF5 lets a dataset keep its bytes in other files (external storage, virtual datasets) and a group link to
objects of another file (external links). Read through such a file, a label file would pull in whatever
local file it names (``node_names`` stored in ``/home/you/.ssh/id_rsa``); s3k refuses them, naming the
object and the file it points to.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import h5py

from s3k.base.errors import UserError

__all__ = ["check_self_contained", "open_hdf5"]


def check_self_contained(h5: Any, path: str | Path) -> None:
    """Raise :class:`UserError` when the open ``h5py.File`` ``h5`` has an external link, a dataset stored in
    other files or a virtual dataset."""
    links: list[str] = []
    h5.visit_links(links.append)  # links of every group reached inside the file; none followed outside
    for name in links:
        link = h5.get(name, getlink=True)
        if isinstance(link, h5py.ExternalLink):
            raise UserError(f"{path}: {name!r} links to {link.filename!r}; s3k reads only what a file holds "
                            "itself (an external link could read any file)")

    def check(name: str, obj: Any) -> None:
        if not isinstance(obj, h5py.Dataset):
            return
        if obj.is_virtual:
            raise UserError(f"{path}: dataset {name!r} is virtual (its data lie in other files); s3k reads "
                            "only what a file holds itself")
        plist = obj.id.get_create_plist()
        if plist.get_external_count() > 0:
            other = plist.get_external(0)[0].decode(errors="replace")
            raise UserError(f"{path}: dataset {name!r} keeps its data in {other!r} (external storage); s3k "
                            "reads only what a file holds itself")

    h5.visititems(check)


def open_hdf5(path: str | Path, what: str = "HDF5") -> Any:
    """``h5py.File(path, "r")``, refused in one line (naming ``what`` the file should be) when it is not an
    HDF5 file or is not self-contained (:func:`check_self_contained`)."""
    try:
        h5 = h5py.File(path, "r")
    except OSError as exc:
        raise UserError(f"{path}: not an {what} file ({exc})") from None
    try:
        check_self_contained(h5, path)
    except BaseException:
        h5.close()
        raise
    return h5
