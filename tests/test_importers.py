"""Importers: each parser on tiny files written here in the peer tool's own layout, then ``s3k import``."""

import textwrap

import cv2
import numpy as np
import pytest

from s3k.data import importers as imp

# ------------------------------------------------------------------------------------------------------------
# anipose calibration.toml

TOML = """\
[cam_0]
name = "left"
size = [ 64, 48,]
matrix = [ [ 80.0, 0.0, 31.5,], [ 0.0, 81.0, 23.5,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.1, 0.01, 0.0, 0.0, 0.0,]
rotation = [ 0.1, -0.2, 0.05,]
translation = [ 10.0, -5.0, 300.0,]

[cam_1]
name = "right"
size = [ 64, 48,]
matrix = [ [ 90.0, 0.0, 32.0,], [ 0.0, 90.0, 24.0,], [ 0.0, 0.0, 1.0,],]
distortions = [ 0.0, 0.0, 0.0, 0.0, 0.0,]
rotation = [ 0.0, 1.2, 0.0,]
translation = [ -250.0, 0.0, 200.0,]

[metadata]
board_x = 8
board_y = 11
square_length = 24.0
"""


def test_read_anipose_calibration(tmp_path):
    path = tmp_path / "calibration.toml"
    path.write_text(TOML)
    calib = imp.read_anipose_calibration(path)
    assert calib.names == ["left", "right"]
    assert calib.units == "mm"  # square_length 24 in the board's unit
    np.testing.assert_array_equal(calib.size, [[64, 48], [64, 48]])
    np.testing.assert_allclose(calib.K[0], [[80, 0, 31.5], [0, 81, 23.5], [0, 0, 1]])
    np.testing.assert_allclose(calib.dist[0], [-0.1, 0.01, 0, 0, 0])
    np.testing.assert_allclose(calib.R[0], cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))[0], atol=1e-12)
    np.testing.assert_allclose(calib.R[1], cv2.Rodrigues(np.array([0.0, 1.2, 0.0]))[0], atol=1e-12)
    np.testing.assert_allclose(calib.t[1], [-250, 0, 200])
    # Camera centre: the point that maps to the camera origin.
    np.testing.assert_allclose(calib.R[1] @ calib.centres()[1] + calib.t[1], 0, atol=1e-9)
    right = calib.select(["right"])
    assert right.names == ["right"] and right.K.shape == (1, 3, 3)
    with pytest.raises(KeyError, match="'middle'.*left, right"):
        calib.select(["middle"])


def test_anipose_round_trip(tmp_path):
    path = tmp_path / "calibration.toml"
    path.write_text(TOML)
    calib = imp.read_anipose_calibration(path)
    out = tmp_path / "out" / "calibration.toml"
    out.parent.mkdir()
    imp.write_anipose_calibration(out, calib)
    again = imp.read_anipose_calibration(out)  # no board.toml there: the unit comes from the metadata
    assert again.names == calib.names and again.units == "mm"
    for name in ("K", "dist", "R", "t", "size"):
        np.testing.assert_allclose(getattr(again, name), getattr(calib, name), atol=1e-12, err_msg=name)
    assert again.metadata["square_length"] == 24.0


def test_units_from_board_toml(tmp_path):
    path = tmp_path / "calibration.toml"
    path.write_text(TOML.split("[metadata]")[0])
    assert imp.read_anipose_calibration(path).units == "unknown"
    (tmp_path / "board.toml").write_text("board_x = 8\nboard_y = 11\nsquare_length = 0.024\n")
    assert imp.read_anipose_calibration(path).units == "m"
    assert imp.read_anipose_calibration(path, units="cm").units == "cm"


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda s: s.replace("[ [ 90.0, 0.0, 32.0,], ", "[ "), r"\[cam_1\] matrix has shape"),
        (lambda s: s.replace('rotation = [ 0.0, 1.2, 0.0,]\n', ""), r"\[cam_1\] has no field 'rotation'"),
        (lambda s: s.replace("size = [ 64, 48,]", "size = [ 64, -48,]", 1), r"\[cam_0\] size"),
        (lambda s: s.replace('name = "right"', 'name = "left"'), "'left' appears twice"),
        (lambda s: s.replace("translation = [ 10.0", "translation = [ 'a'"), r"\[cam_0\] translation"),
        (lambda s: s.replace("[cam_1]", "[cam_1]\nfisheye = true"), "fisheye"),
        (lambda s: s.replace("[cam_1]", "[cam_1"), "not valid TOML"),
    ],
)
def test_anipose_malformed(tmp_path, edit, match):
    path = tmp_path / "calibration.toml"
    path.write_text(edit(TOML))
    with pytest.raises(ValueError, match=match) as info:
        imp.read_anipose_calibration(path)
    assert "calibration.toml" in str(info.value)


def test_anipose_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.toml"):
        imp.read_anipose_calibration(tmp_path / "nope.toml")


# ------------------------------------------------------------------------------------------------------------
# DeepLabCut / Lightning Pose CSV

DLC = """\
scorer,anna,anna,anna,anna,anna,anna
bodyparts,nose,nose,ear,ear,tail,tail
coords,x,y,x,y,x,y
labeled-data/session1_top/img0042.png,10.5,20.25,30,40,,
labeled-data/session1_top/img0007.png,,,31,41.5,50,60
labeled-data/session1_top/img0100.png,1,2,,3,NaN,NaN
"""


def test_read_dlc_csv(tmp_path):
    path = tmp_path / "CollectedData_top.csv"
    path.write_text(DLC)
    table = imp.read_dlc_csv(path)
    assert table.keypoints == ["nose", "ear", "tail"]
    np.testing.assert_array_equal(table.frame_ids, [7, 42, 100])  # from image names, sorted
    assert table.uv.shape == (3, 3, 2)
    np.testing.assert_array_equal(table.uv[1], [[10.5, 20.25], [30, 40], [np.nan, np.nan]])
    np.testing.assert_array_equal(table.uv[0, 0], [np.nan, np.nan])
    # A keypoint with only one coordinate is unlabelled.
    np.testing.assert_array_equal(table.uv[2, 1], [np.nan, np.nan])
    np.testing.assert_array_equal(table.uv[2, 2], [np.nan, np.nan])
    dense = table.dense(101, ["tail", "nose"])
    assert dense.shape == (101, 2, 2)
    np.testing.assert_array_equal(dense[7, 0], [50, 60])
    assert np.isnan(dense[8]).all()
    by_row = imp.read_dlc_csv(path, frame_ids_from="row")
    np.testing.assert_array_equal(by_row.frame_ids, [0, 1, 2])


def test_read_dlc_csv_split_index_columns_and_likelihood(tmp_path):
    # DeepLabCut >= 2.2 writes the image path as three index columns; prediction CSVs add a likelihood.
    text = textwrap.dedent(
        """\
        scorer,,,net,net,net
        bodyparts,,,nose,nose,nose
        coords,,,x,y,likelihood
        labeled-data,vid1,img003.png,5,6,0.9
        labeled-data,vid1,img001.png,7,8,0.2
        """
    )
    path = tmp_path / "CollectedData.csv"
    path.write_text(text)
    table = imp.read_dlc_csv(path)
    assert table.keypoints == ["nose"]
    np.testing.assert_array_equal(table.frame_ids, [1, 3])
    np.testing.assert_array_equal(table.uv[:, 0], [[7, 8], [5, 6]])


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda s: s.replace("31,41.5", "31,abc"), r"line 5 .*img0007.*'ear' y: 'abc'"),
        (lambda s: s.replace("coords,x,y,x,y,x,y\n", ""), "'coords' header row"),
        (lambda s: s.replace("coords,x,y,x,y,x,y", "coords,x,y,x,z,x,y"), "column 5 is 'z'"),
        (lambda s: s.replace("img0100", "img0042"), r"frame ids \[42\]"),
        (lambda s: s.replace("NaN,NaN", "NaN,NaN,7"), "line 6 has 8 cells"),
        (lambda s: s.split("labeled-data")[0], "no label rows"),
    ],
)
def test_dlc_malformed(tmp_path, edit, match):
    path = tmp_path / "labels.csv"
    path.write_text(edit(DLC))
    with pytest.raises(ValueError, match=match) as info:
        imp.read_dlc_csv(path)
    assert "labels.csv" in str(info.value)


def test_lightning_pose_multiview_layout(tmp_path):
    for view in ("top", "side"):
        (tmp_path / f"CollectedData_{view}.csv").write_text(DLC)
    found = imp.find_lightning_pose_csvs(tmp_path, ["top", "side"])
    assert found["side"].name == "CollectedData_side.csv"
    with pytest.raises(FileNotFoundError, match="CollectedData_back.csv"):
        imp.find_lightning_pose_csvs(tmp_path, ["back"])


def test_frame_id_from_path():
    assert imp.frame_id_from_path("labeled-data/s1_cam2/img0042.png") == 42
    assert imp.frame_id_from_path("C:\\data\\cam2\\frame_12_000031.jpg") == 31
    assert imp.frame_id_from_path("labeled-data/s1/image.png") is None


# ------------------------------------------------------------------------------------------------------------
# SLEAP analysis HDF5


def _write_sleap(path, locations, occupancy=None, nodes=("head", "body", "tail"), transpose=True, names=None):
    """SLEAP's writer: ``locations (F, K, 2, T)``, stored transposed (MATLAB order) by default."""
    import h5py

    F, K, _, T = locations.shape
    if occupancy is None:
        occupancy = np.ones((T, F), dtype=np.uint8)  # SLEAP builds (tracks, frames) then transposes
    names = names or [f"track_{i}" for i in range(T)]
    with h5py.File(path, "w") as f:
        f["tracks"] = locations.T if transpose else locations
        f["track_occupancy"] = occupancy.T if transpose else occupancy
        f["node_names"] = np.array([n.encode() for n in nodes], dtype="S")
        f["track_names"] = np.array([n.encode() for n in names], dtype="S")
        f["point_scores"] = np.ones((F, K, T)).T
        f["video_path"] = "cam.mp4"


def _locations(F=5, K=3, T=1, seed=0):
    loc = np.random.default_rng(seed).uniform(0, 60, (F, K, 2, T))
    loc[1, 2, :, 0] = np.nan  # a missing node
    return loc


def test_read_sleap_analysis(tmp_path):
    loc = _locations()
    path = tmp_path / "cam.analysis.h5"
    _write_sleap(path, loc)
    table = imp.read_sleap_analysis(path)
    assert table.keypoints == ["head", "body", "tail"]
    np.testing.assert_array_equal(table.frame_ids, np.arange(5))
    np.testing.assert_array_equal(table.uv, loc[..., 0])
    assert np.isnan(table.uv[1, 2]).all()


def test_read_sleap_untransposed_and_tracks(tmp_path):
    loc = _locations(T=2)
    occupancy = np.ones((2, 5), dtype=np.uint8)
    occupancy[1, 3] = 0
    path = tmp_path / "cam.h5"
    _write_sleap(path, loc, occupancy, transpose=False, names=["mouse_a", "mouse_b"])
    with pytest.raises(ValueError, match="2 tracks \\(mouse_a, mouse_b\\)"):
        imp.read_sleap_analysis(path)
    table = imp.read_sleap_analysis(path, track="mouse_b")
    np.testing.assert_array_equal(table.uv[[0, 1, 2, 4]], loc[[0, 1, 2, 4], :, :, 1])
    assert np.isnan(table.uv[3]).all()  # track not occupied in frame 3
    np.testing.assert_array_equal(imp.read_sleap_analysis(path, track=0).uv, loc[..., 0])
    with pytest.raises(ValueError, match="no track 'mouse_c'"):
        imp.read_sleap_analysis(path, track="mouse_c")


def test_sleap_malformed(tmp_path):
    import h5py

    path = tmp_path / "bad.h5"
    with h5py.File(path, "w") as f:
        f["tracks"] = np.zeros((1, 2, 4, 5))
        f["node_names"] = np.array([b"a", b"b", b"c"])
    with pytest.raises(ValueError, match=r"bad.h5: 'tracks' has shape \(1, 2, 4, 5\)"):
        imp.read_sleap_analysis(path)
    with h5py.File(path, "w") as f:
        f["tracks"] = np.zeros((1, 2, 3, 5))
    with pytest.raises(ValueError, match="bad.h5: no 'node_names'"):
        imp.read_sleap_analysis(path)
    text = tmp_path / "text.h5"
    text.write_text("hello")
    with pytest.raises(ValueError, match="text.h5: not an HDF5 file"):
        imp.read_sleap_analysis(text)
