"""Sizes and counts are checked before anything is allocated: image sizes from file headers, frame counts
against memory, request bodies, pickles, HDF5 files that would read other files."""

from __future__ import annotations

import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers.recordings import CAMS
from helpers.synthetic_rig import count_decodes, make_dataset

from s3k import cli
from s3k.data.images import header_size


def big_png(path: Path, W: int = 30000, H: int = 30000) -> Path:
    """A valid 1-bit greyscale PNG of W x H pixels (a few MB on disk; decoded as RGB, 3 W H bytes)."""
    comp = zlib.compressobj(9)
    row = b"\x00" * (1 + (W + 7) // 8)  # filter byte, then the row's bits
    idat = b"".join(comp.compress(row) for _ in range(H)) + comp.flush()

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    ihdr = struct.pack(">IIBBBBB", W, H, 1, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b""))
    return path


@pytest.fixture(scope="module")
def huge_image_dataset(tmp_path_factory):
    data = make_dataset(tmp_path_factory.mktemp("huge") / "ds", size=32, labelled=2, unlabelled=1, test=0)
    big_png(sorted((data / "images" / "cam1").glob("*.png"))[0])
    return data


def test_header_sizes_of_png_and_jpeg(tmp_path):
    image = np.zeros((48, 64, 3), np.uint8)
    for suffix in (".png", ".jpg"):
        cv2.imwrite(str(tmp_path / f"a{suffix}"), image)
        assert header_size(tmp_path / f"a{suffix}") == (64, 48)
    (tmp_path / "b.txt").write_text("not an image")
    assert header_size(tmp_path / "b.txt") is None


def test_validate_reads_a_huge_image_size_from_its_header(huge_image_dataset, capsys, monkeypatch):
    import s3k.data.checks as dataset_module  # the module that checks every image

    decoded = count_decodes(monkeypatch, dataset_module)
    assert cli.main(["validate", str(huge_image_dataset), "--workers", "1"]) == 1
    out = capsys.readouterr().out
    assert "image is 30000x30000, s3k.json image_size is 32x32" in out
    assert decoded and not any(n.startswith("images/cam1/000000") for n in decoded)  # the others are decoded


def test_validate_of_a_huge_image_stays_small_in_memory(huge_image_dataset):
    """Decoded, the 30000 px image takes 2.7 GB; read from its header, validate stays far below 1 GB."""
    # the command's own peak, read in its process after the peak is reset (a child's ru_maxrss starts from the
    # forking test process's resident size, which grows with every test before it)
    script = ("import sys\nopen('/proc/self/clear_refs', 'w').write('5')\nfrom s3k import cli\n"
              "rc = cli.main(sys.argv[1:])\nhwm = [line for line in open('/proc/self/status') if "
              "line.startswith('VmHWM')][0]\nprint('peak_kib', hwm.split()[1])\nsys.exit(rc)")
    proc = subprocess.run([sys.executable, "-c", script, "validate", str(huge_image_dataset), "--workers",
                           "1"], capture_output=True, text=True)
    assert proc.returncode == 1 and "30000x30000" in proc.stdout
    peak_kib = int(proc.stdout.split("peak_kib")[-1].split()[0])
    assert peak_kib < 1024 * 1024


def test_a_huge_image_is_refused_before_it_is_decoded(tmp_path):
    from s3k.data.sources import ImageReadError, decode_image

    with pytest.raises(ImageReadError, match="30000x30000"):
        decode_image(big_png(tmp_path / "big.png"))


def test_simulate_refuses_frame_counts_that_do_not_fit_in_memory(tmp_path, capsys):
    out = tmp_path / "ds"
    assert cli.main(["simulate", "box", "--out", str(out), "--test", "1000000000", "--workers", "1"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "GiB" in err and "--test" in err
    assert not out.exists() and list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------------------------
# HDF5 label files read only what they hold


def _sleap_file(path: Path, tracks: np.ndarray, names=None, external: Path | None = None,
                link: Path | None = None) -> Path:
    import h5py

    with h5py.File(path, "w") as h5:
        h5["tracks"] = tracks
        if external is not None:  # node_names' bytes kept in another file
            size = external.stat().st_size
            h5.create_dataset("node_names", shape=(size,), dtype="S1", external=[(str(external), 0, size)])
        else:
            h5["node_names"] = np.array(names)
        if link is not None:
            h5["elsewhere"] = h5py.ExternalLink(str(link), "/data")
    return path


def test_import_refuses_a_sleap_file_with_external_storage(import_recording, tmp_path, capsys):
    import h5py

    secret = tmp_path / "secret.txt"
    secret.write_text("private text")
    root = import_recording["root"]
    files = []
    for cam in CAMS:
        with h5py.File(root / f"{cam}.analysis.h5") as h5:
            tracks = h5["tracks"][()]
        path = tmp_path / f"{cam}.h5"
        _sleap_file(path, tracks, names=[b"head", b"body", b"tail"],
                    external=secret if cam == "east" else None)
        files.append(f"{cam}={path}")
    out = tmp_path / "ds"
    argv = ["import", "--calibration", str(root / "calibration.toml"), "--videos",
            *[f"{cam}={root / cam}.mkv" for cam in CAMS], "--sleap", *files, "--out", str(out)]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "external storage" in err and "east.h5" in err
    assert "private text" not in err and not out.exists()


@pytest.mark.parametrize("names, link, match", [
    ([b"head", b"head"], False, "more than once"),
    ([b"head", b"b\xe9te"], False, "not UTF-8"),
    ([b"head", b"tail"], True, "links to"),
])
def test_sleap_files_with_foreign_or_broken_names_are_one_line(tmp_path, names, link, match):
    from s3k.base.errors import UserError
    from s3k.data.formats.sleap import read_sleap_analysis

    path = _sleap_file(tmp_path / "a.h5", np.zeros((1, 2, 2, 3)), names=names,
                       link=tmp_path / "other.h5" if link else None)
    with pytest.raises(UserError, match=match):
        read_sleap_analysis(path)


# ------------------------------------------------------------------------------------------------------------
# Pickles allocate no more than they hold


@pytest.mark.parametrize("call", ["_reconstruct", "ndarray"])
def test_a_tiny_pickle_cannot_ask_for_gigabytes(tmp_path, call):
    import pickle

    from s3k.base.errors import UserError
    from s3k.data.formats.safe_pickle import load_pickle

    shape = pickle.dumps((2**36,), protocol=2)[2:-1]  # (68719476736,): 64 GiB of int8
    if call == "_reconstruct":
        data = b"\x80\x02cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\n" + shape + b"U\x01b\x87R."
    else:
        data = b"\x80\x02cnumpy\nndarray\n" + shape + b"\x85R."
    assert len(data) <= 70
    path = tmp_path / "df3d_result.pkl"
    path.write_bytes(data)
    with pytest.raises(UserError, match="asks for an array of .* bytes"):
        load_pickle(path)


def test_pickled_arrays_still_load(tmp_path):
    import pickle

    from s3k.data.formats.safe_pickle import load_pickle

    obj = {"points2d": np.arange(24.0).reshape(2, 3, 4), "names": np.array(["a", "b"], dtype=object),
           "empty": np.zeros((0, 3)), "fortran": np.asfortranarray(np.ones((2, 3)))}
    for protocol in (3, 4, 5):
        (tmp_path / "a.pkl").write_bytes(pickle.dumps(obj, protocol=protocol))
        back = load_pickle(tmp_path / "a.pkl")
        assert all(np.array_equal(back[k], v) for k, v in obj.items())
