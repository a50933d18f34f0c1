"""Importers: each parser on tiny files written here in the peer tool's own layout, then ``s3k import``."""

import textwrap

import cv2
import numpy as np
import pytest
import torch
from helpers.real_recording import REAL, needs_real
from helpers.recordings import CAMS, KEYPOINTS, N_FRAMES, run_import, write_sleap

from s3k.base.errors import UserError
from s3k.cli.options import camera_pairs, parse_crops, parse_size
from s3k.data import recording as rec
from s3k.data.formats import anipose, dlc, labels2d, sleap
from s3k.data.import_labels import LABEL_FORMATS, SleapFiles
from s3k.data.rig import Rig
from s3k.geometry import Cameras

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
    calib = anipose.read_anipose_calibration(path)
    assert calib.names == ["left", "right"]
    assert calib.units == "mm"  # square_length 24 in the board's unit
    np.testing.assert_array_equal(calib.size, [[64, 48], [64, 48]])
    cams = calib.cameras.numpy()
    np.testing.assert_allclose(cams["K"][0], [[80, 0, 31.5], [0, 81, 23.5], [0, 0, 1]])
    np.testing.assert_allclose(cams["dist"][0], [-0.1, 0.01, 0, 0, 0])
    np.testing.assert_allclose(cams["R"][0], cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))[0], atol=1e-12)
    np.testing.assert_allclose(cams["R"][1], cv2.Rodrigues(np.array([0.0, 1.2, 0.0]))[0], atol=1e-12)
    np.testing.assert_allclose(cams["t"][1], [-250, 0, 200])
    # Camera centre: the point that maps to the camera origin.
    centre = calib.cameras.centres().numpy()[1]
    np.testing.assert_allclose(cams["R"][1] @ centre + cams["t"][1], 0, atol=1e-9)
    right = calib.select(["right"])
    assert right.names == ["right"] and tuple(right.cameras.K.shape) == (1, 3, 3)
    np.testing.assert_array_equal(right.cameras.K.numpy()[0], cams["K"][1])
    with pytest.raises(KeyError, match="'middle'.*left, right"):
        calib.select(["middle"])


def test_anipose_round_trip(tmp_path):
    path = tmp_path / "calibration.toml"
    path.write_text(TOML)
    calib = anipose.read_anipose_calibration(path)
    out = tmp_path / "out" / "calibration.toml"
    out.parent.mkdir()
    anipose.write_anipose_calibration(out, calib)
    again = anipose.read_anipose_calibration(out)  # no board.toml there: the unit comes from the metadata
    assert again.names == calib.names and again.units == "mm"
    np.testing.assert_array_equal(again.size, calib.size)
    for name, value in again.cameras.numpy().items():
        np.testing.assert_allclose(value, calib.cameras.numpy()[name], atol=1e-12, err_msg=name)
    assert again.metadata["square_length"] == 24.0


def test_units_from_board_toml(tmp_path):
    path = tmp_path / "calibration.toml"
    path.write_text(TOML.split("[metadata]")[0])
    assert anipose.read_anipose_calibration(path).units == "unknown"
    (tmp_path / "board.toml").write_text("board_x = 8\nboard_y = 11\nsquare_length = 0.024\n")
    assert anipose.read_anipose_calibration(path).units == "m"
    assert anipose.read_anipose_calibration(path, units="cm").units == "cm"


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
        (lambda s: s.replace("distortions = [ -0.1", "distortions = [ 'a'"),
         r"calibration.toml: \[cam_0\] distortions must be numbers, got \['a', "),
        (lambda s: "[board]\nsquare_length = 24.0\n", "not an anipose calibration: no camera sections"),
    ],
)
def test_anipose_malformed(tmp_path, edit, match):
    path = tmp_path / "calibration.toml"
    path.write_text(edit(TOML))
    with pytest.raises(UserError, match=match) as info:
        anipose.read_anipose_calibration(path)
    assert "calibration.toml" in str(info.value) and "\n" not in str(info.value)


def test_bad_calibration_value_is_one_line_naming_file_section_field(tmp_path, capsys):
    from s3k.cli import main

    path = tmp_path / "calibration.toml"
    path.write_text(TOML.replace("distortions = [ -0.1", "distortions = [ 'a'"))
    code = main(["import", "--calibration", str(path), "--videos", "left=l.mkv", "right=r.mkv",
                 "--sleap", "left=l.h5", "--out", str(tmp_path / "ds")])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    assert err.strip().splitlines() == [
        f"s3k import: error: {path}: [cam_0] distortions must be numbers, got ['a', 0.01, 0.0, 0.0, 0.0]"
    ]


def test_anipose_reads_a_rotation_matrix_in_place_of_a_rodrigues_vector(tmp_path):
    """Some tools write each camera's world->camera rotation as a 3x3 matrix under ``rotation``: read it as
    that rotation (a matrix that is no rotation is still refused)."""
    R1 = cv2.Rodrigues(np.array([0.0, 1.2, 0.0]))[0]
    matrix = "[ " + ", ".join("[ " + ", ".join(repr(float(v)) for v in row) + ",]" for row in R1) + ",]"
    path = tmp_path / "calibration.toml"
    path.write_text(TOML.replace("rotation = [ 0.0, 1.2, 0.0,]", f"rotation = {matrix}"))
    calib = anipose.read_anipose_calibration(path)
    np.testing.assert_allclose(calib.cameras.numpy()["R"][1], R1, atol=1e-15)
    ref = anipose.read_anipose_calibration(_written(tmp_path / "ref", TOML))
    np.testing.assert_allclose(calib.cameras.numpy()["R"], ref.cameras.numpy()["R"], atol=1e-12)
    scaled = matrix.replace("1.0", "2.0")
    path.write_text(TOML.replace("rotation = [ 0.0, 1.2, 0.0,]", f"rotation = {scaled}"))
    with pytest.raises(UserError, match=r"camera right: rotation \(R\) not a rotation"):
        anipose.read_anipose_calibration(path)
    path.write_text(TOML.replace("rotation = [ 0.0, 1.2, 0.0,]", "rotation = [ 0.0, 1.2,]"))
    with pytest.raises(UserError, match=r"\[cam_1\] rotation has shape \(2,\), expected \(3,\) .* or "
                                        r"\(3, 3\)"):
        anipose.read_anipose_calibration(path)


def test_calibration_with_absurd_translations_is_refused(tmp_path, capsys):
    """Translations of 1e308 are finite but beyond any rig: refused in one line, not imported with a units
    warning."""
    from s3k.cli import main

    path = tmp_path / "calibration.toml"
    path.write_text(TOML.replace("translation = [ -250.0, 0.0, 200.0,]",
                                 "translation = [ 1e308, 0.0, 1e308,]"))
    with pytest.raises(UserError, match=r"camera right: translation \(t\) \[1e\+308, 0.0, 1e\+308\] is "
                                        "beyond any rig"):
        anipose.read_anipose_calibration(path)
    code = main(["import", "--calibration", str(path), "--videos", "left=l.mkv", "right=r.mkv",
                 "--sleap", "left=l.h5", "--out", str(tmp_path / "ds")])
    err = capsys.readouterr().err
    assert code == 1 and len(err.strip().splitlines()) == 1 and "beyond any rig" in err
    assert not (tmp_path / "ds").exists()


def _written(folder, text):
    folder.mkdir()
    (folder / "calibration.toml").write_text(text)
    return folder / "calibration.toml"


def test_anipose_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.toml"):
        anipose.read_anipose_calibration(tmp_path / "nope.toml")


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
    table = dlc.read_dlc_csv(path)
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
    by_row = dlc.read_dlc_csv(path, frame_ids_from="row")
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
    table = dlc.read_dlc_csv(path)
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
        dlc.read_dlc_csv(path)
    assert "labels.csv" in str(info.value)


def test_lightning_pose_multiview_layout(tmp_path):
    for view in ("top", "side"):
        (tmp_path / f"CollectedData_{view}.csv").write_text(DLC)
    found = dlc.find_lightning_pose_csvs(tmp_path, ["top", "side"])
    assert found["side"].name == "CollectedData_side.csv"
    with pytest.raises(FileNotFoundError, match="CollectedData_back.csv"):
        dlc.find_lightning_pose_csvs(tmp_path, ["back"])


def test_frame_id_from_path():
    assert labels2d.frame_id_from_path("labeled-data/s1_cam2/img0042.png") == 42
    assert labels2d.frame_id_from_path("C:\\data\\cam2\\frame_12_000031.jpg") == 31
    assert labels2d.frame_id_from_path("labeled-data/s1/image.png") is None


# ------------------------------------------------------------------------------------------------------------
# SLEAP analysis HDF5


def _locations(F=5, K=3, T=1, seed=0):
    loc = np.random.default_rng(seed).uniform(0, 60, (F, K, 2, T))
    loc[1, 2, :, 0] = np.nan  # a missing node
    return loc


def test_read_sleap_analysis(tmp_path):
    loc = _locations()
    path = tmp_path / "cam.analysis.h5"
    write_sleap(path, loc)
    table = sleap.read_sleap_analysis(path)
    assert table.keypoints == ["head", "body", "tail"]
    np.testing.assert_array_equal(table.frame_ids, np.arange(5))
    np.testing.assert_array_equal(table.uv, loc[..., 0])
    assert np.isnan(table.uv[1, 2]).all()


def test_read_sleap_untransposed_and_tracks(tmp_path):
    loc = _locations(T=2)
    occupancy = np.ones((2, 5), dtype=np.uint8)
    occupancy[1, 3] = 0
    path = tmp_path / "cam.h5"
    write_sleap(path, loc, occupancy, transpose=False, names=["mouse_a", "mouse_b"])
    with pytest.raises(ValueError, match="2 tracks \\(mouse_a, mouse_b\\)"):
        sleap.read_sleap_analysis(path)
    table = sleap.read_sleap_analysis(path, track="mouse_b")
    np.testing.assert_array_equal(table.uv[[0, 1, 2, 4]], loc[[0, 1, 2, 4], :, :, 1])
    assert np.isnan(table.uv[3]).all()  # track not occupied in frame 3
    np.testing.assert_array_equal(sleap.read_sleap_analysis(path, track=0).uv, loc[..., 0])
    with pytest.raises(ValueError, match="no track 'mouse_c'"):
        sleap.read_sleap_analysis(path, track="mouse_c")


def test_sleap_malformed(tmp_path):
    import h5py

    path = tmp_path / "bad.h5"
    with h5py.File(path, "w") as f:
        f["tracks"] = np.zeros((1, 2, 4, 5))
        f["node_names"] = np.array([b"a", b"b", b"c"])
    with pytest.raises(ValueError, match=r"bad.h5: 'tracks' has shape \(1, 2, 4, 5\)"):
        sleap.read_sleap_analysis(path)
    with h5py.File(path, "w") as f:
        f["tracks"] = np.zeros((1, 2, 3, 5))
    with pytest.raises(ValueError, match="bad.h5: no 'node_names'"):
        sleap.read_sleap_analysis(path)
    text = tmp_path / "text.h5"
    text.write_text("hello")
    with pytest.raises(ValueError, match="text.h5: not an HDF5 file"):
        sleap.read_sleap_analysis(text)


# ------------------------------------------------------------------------------------------------------------
# s3k import, end to end on a tiny synthetic recording


def _reprojected(ds, frame_ids, X):
    """Project ground-truth points with the dataset's calibration: must land on its labels."""
    import torch

    from s3k.geometry import project

    cams = ds.calibration(frame_ids, dtype=np.float64)
    uv, _ = project(cams, torch.as_tensor(X[frame_ids][:, None], dtype=torch.float64))
    return uv.numpy()


def test_import_sleap(import_recording, tmp_path, capsys):
    from s3k.data import Dataset
    from s3k.geometry.warp import resize_crop

    out = tmp_path / "ds"
    assert run_import(import_recording, out, "--labelled", "3", "--test", "4", "--seed", "1", "--scale",
                      "0.5") == 0
    assert "labelled 3, test 4, unlabelled 5" in capsys.readouterr().out
    ds = Dataset.open(out)
    assert ds.cameras == CAMS and ds.keypoints == KEYPOINTS
    assert ds.image_size == (32, 24) and ds.units == "mm"
    lab, test, unl = ds.frames("labelled"), ds.frames("test"), ds.frames("unlabelled")
    assert len(lab) == 3 and len(test) == 4 and len(unl) == 5
    assert sorted([*lab, *test, *unl]) == list(range(N_FRAMES))
    # Labels are kept on labelled and test frames only, and follow the resize exactly (K' = M K).
    ids = np.sort(np.concatenate([lab, test]))
    uv, mask = ds.labels(ids)
    ref = import_recording["uv"][ids]
    np.testing.assert_array_equal(mask, np.isfinite(ref).all(-1))
    np.testing.assert_allclose(uv[mask], _reprojected(ds, ids, import_recording["X"])[mask], atol=1e-3)
    np.testing.assert_allclose(uv[mask], (0.5 * (ref + 0.5) - 0.5)[mask], atol=1e-3)
    assert not ds.labels(unl)[1].any()
    # Images: the right video frame of the right camera, resized by resize_crop.
    f = int(test[0])
    images = ds.images([f])[0]
    for c, cam in enumerate(CAMS):
        expected = resize_crop(import_recording["frames"][cam][f], None, None, (32, 24))[0]
        np.testing.assert_array_equal(images[c], expected)
    # The same seed gives the same split.
    assert run_import(import_recording, tmp_path / "again", "--labelled", "3", "--test", "4", "--seed", "1",
                      "--stride", "4") == 0
    again = Dataset.open(tmp_path / "again")
    np.testing.assert_array_equal(again.frames("test"), test)
    np.testing.assert_array_equal(again.frames("unlabelled"), [f for f in unl if f % 4 == 0])


def test_import_recording_takes_typed_arguments(import_recording, tmp_path):
    """The library call gives the dataset the command line gives for the same options."""
    from s3k.data import Dataset

    root = import_recording["root"]
    path = rec.import_recording(
        root / "calibration.toml", {cam: root / f"{cam}.mkv" for cam in CAMS}, tmp_path / "lib",
        SleapFiles({cam: root / f"{cam}.analysis.h5" for cam in CAMS}),
        split=rec.SplitOptions(labelled=3, test=2, seed=1),
        images=rec.ImageOptions(size=(32, 24), crops={"north": (8.0, 4.0, 56.0, 40.0)}),
        keypoints=["tail", "head"],
    )
    assert path == tmp_path / "lib"
    assert run_import(import_recording, tmp_path / "cli", "--labelled", "3", "--test", "2", "--seed", "1",
                      "--size", "32,24", "--crop", "north=8,4,56,40", "--keypoints", "tail,head") == 0
    lib, cli = Dataset.open(path, cache="none"), Dataset.open(tmp_path / "cli", cache="none")
    assert lib.keypoints == ["tail", "head"] and lib.cameras == CAMS
    for split in ("labelled", "test", "unlabelled"):
        np.testing.assert_array_equal(lib.frames(split), cli.frames(split))
    ids = lib.frames()
    np.testing.assert_array_equal(lib.labels(ids)[0], cli.labels(ids)[0])
    np.testing.assert_array_equal(lib.calibration(ids).K.numpy(), cli.calibration(ids).K.numpy())
    with pytest.raises(UserError, match="no labels given: name the keypoints with --keypoints"):
        rec.import_recording(root / "calibration.toml", {"north": root / "north.mkv"}, tmp_path / "x")
    with pytest.raises(UserError, match=r"labels given for cameras \['south'\] that have no --videos entry"):
        rec.import_recording(root / "calibration.toml", {"north": root / "north.mkv"}, tmp_path / "x",
                             SleapFiles({"south": root / "south.analysis.h5"}))
    assert set(LABEL_FORMATS) == {"sleap", "sleap-project", "nwb", "deeplabcut", "lightning-pose", "openpose",
                                  "mmpose", "deepfly3d"}


def test_import_dlc_and_lightning_pose_with_crop(import_recording, tmp_path):
    from s3k.data import Dataset

    crop = ["north=8,4,56,40", "east=0,0,48,36"]  # two crop sizes (48x36 each), one camera uncropped
    for labels in ("dlc", "lightning-pose"):
        out = tmp_path / labels
        code = run_import(import_recording, out, "--labelled", "all", "--test", "2", "--crop", *crop,
                          "--size", "32,24", labels=labels)
        assert code == 0
        ds = Dataset.open(out)
        assert ds.image_size == (32, 24)
        ids = np.sort(np.concatenate([ds.frames("labelled"), ds.frames("test")]))
        np.testing.assert_array_equal(ids, np.arange(0, N_FRAMES, 2))  # only labelled frames can be chosen
        uv, mask = ds.labels(ids)
        np.testing.assert_allclose(uv[mask], _reprojected(ds, ids, import_recording["X"])[mask], atol=1e-3)
        # Labels outside a crop are dropped, the others kept.
        ref = import_recording["uv"][ids]
        u, v = ref[:, 0, :, 0], ref[:, 0, :, 1]
        inside = (u >= 8) & (u < 56) & (v >= 4) & (v < 40)
        np.testing.assert_array_equal(mask[:, 0], inside & np.isfinite(ref[:, 0]).all(-1))


def test_import_says_how_many_labels_it_kept_and_why(import_recording, tmp_path, capsys):
    """The default split keeps 10 labelled frames and no test frame: the import says how many labels that is
    of the recording's, and which options keep more."""
    from s3k.data import Dataset

    out = tmp_path / "ds"
    assert run_import(import_recording, out) == 0
    captured = capsys.readouterr()
    ds = Dataset.open(out)
    kept = int(ds.labels(ds.frames("labelled"))[1].sum())
    total = int(np.isfinite(import_recording["uv"]).all(-1).sum())
    assert kept < total
    assert (f"kept {kept} of the recording's {total} 2D labels: those of 10 labelled frame(s) (--labelled "
            f"10) and 0 test frame(s) (--test 0), chosen among the {N_FRAMES} frames with a keypoint "
            "labelled in >= 2 cameras") in captured.out
    assert f"the other {total - kept} labels, in 2 frame(s), are not written" in captured.out
    assert "--labelled all" in captured.out
    assert "warning: no test frames" in captured.err and "--test N" in captured.err
    assert "calibration" not in captured.err  # a consistent rig: no calibration warning


def test_import_and_validate_warn_of_an_inconsistent_camera(import_recording, tmp_path, capsys):
    """A camera turned by 3 degrees in the calibration disagrees with the labels: import and validate run
    check-calibration's test and name the command that repairs it (validate fails the dataset)."""
    from s3k.cli import main

    root = import_recording["root"]
    rig = anipose.read_anipose_calibration(root / "calibration.toml")
    arrays = rig.cameras.numpy()
    a = np.radians(3.0)
    turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    arrays["R"][2], arrays["t"][2] = turn @ arrays["R"][2], turn @ arrays["t"][2]
    cams = Cameras.from_numpy(arrays["K"], arrays["dist"], arrays["R"], arrays["t"], dtype=torch.float64)
    bad = tmp_path / "turned.toml"
    anipose.write_anipose_calibration(bad, Rig(rig.names, cams, rig.size, rig.units, rig.metadata))
    out = tmp_path / "ds"
    argv = ["import", "--calibration", str(bad), "--videos", *[f"{cam}={root / cam}.mkv" for cam in CAMS],
            "--sleap", *[f"{cam}={root / cam}.analysis.h5" for cam in CAMS], "--labelled", "6", "--test", "4",
            "--out", str(out)]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "warning: calibration: camera(s) south disagree with the others' labels" in err
    assert f"s3k check-calibration {out} --recalibrate flagged" in err
    assert main(["validate", str(out), "--no-images"]) == 1  # training would learn wrong targets there
    report = capsys.readouterr().out
    assert "ERROR   calibration: camera(s) south disagree" in report and "OK:" not in report
    assert f"s3k check-calibration {out} --recalibrate flagged" in report
    assert main(["check-calibration", str(out)]) == 2
    assert f"repair: s3k check-calibration {out} --recalibrate flagged" in capsys.readouterr().out


def test_import_errors(import_recording, tmp_path, capsys):
    root = import_recording["root"]
    # A camera missing from the calibration.
    from s3k.cli import main

    code = main(["import", "--calibration", str(root / "calibration.toml"),
                 "--videos", f"west={root}/north.mkv",
                 "--sleap", f"west={root}/north.analysis.h5", "--out", str(tmp_path / "x")])
    assert code == 1
    assert "camera 'west' is not in the calibration" in capsys.readouterr().err
    # Not enough labelled frames for the split.
    assert run_import(import_recording, tmp_path / "y", "--labelled", "20", labels="dlc") == 1
    assert "--labelled 20" in capsys.readouterr().err
    # A malformed CSV names the file and the line.
    bad = tmp_path / "bad"
    bad.mkdir()
    for cam in CAMS:
        text = (root / f"CollectedData_{cam}.csv").read_text()
        if cam == "east":
            lines = text.splitlines()
            lines[4] = lines[4].replace(".", ",", 1) + ",1"  # one cell too many
            text = "\n".join(lines)
        (bad / f"CollectedData_{cam}.csv").write_text(text)
    code = main(["import", "--calibration", str(root / "calibration.toml"), "--videos",
                 *[f"{cam}={root / cam}.mkv" for cam in CAMS], "--lightning-pose", str(bad),
                 "--out", str(tmp_path / "z")])
    assert code == 1
    assert "CollectedData_east.csv: line 5 has" in capsys.readouterr().err
    # A video whose size disagrees with the calibration.
    from s3k.data.video import write_video

    write_video(tmp_path / "small.mkv", [np.zeros((24, 32, 3), np.uint8)], codec="ffv1")
    code = main(["import", "--calibration", str(root / "calibration.toml"), "--videos",
                 f"north={tmp_path / 'small.mkv'}", "--sleap", f"north={root}/north.analysis.h5",
                 "--out", str(tmp_path / "w")])
    assert code == 1
    assert "small.mkv: video is 32x24" in capsys.readouterr().err




@needs_real
def test_real_recording_files():
    rig = anipose.read_anipose_calibration(REAL / "calibration.toml")
    assert rig.names == ["back", "mid", "side", "top"] and rig.units == "mm"  # from board.toml beside it
    np.testing.assert_array_equal(rig.size, [[1280, 1024]] * 4)
    table = sleap.read_sleap_analysis(REAL / "back" / "minimal_back_proofread.analysis.h5")
    assert table.uv.shape == (120, 15, 2) and len(table.keypoints) == 15 and table.keypoints[0] == "Nose"
    assert 0 < np.isnan(table.uv[..., 0]).mean() < 0.5  # some nodes are not labelled in this view
    ok = np.isfinite(table.uv).all(-1)
    u, v = table.uv[ok].T
    assert (u >= 0).all() and (v >= 0).all() and (u < 1280).all() and (v < 1024).all()


def test_output_size_and_crops():
    full = [(0.0, 0.0, 1280.0, 1024.0)] * 2
    assert rec.output_size(full, None, None) == (1280, 1024)
    assert rec.output_size(full, None, 0.25) == (320, 256)
    assert rec.output_size(full, parse_size("320"), None) == (320, 256)  # the longer side
    assert rec.output_size(full, parse_size("100,80"), None) == (100, 80)
    mixed = [(0.0, 0.0, 100.0, 50.0), (10.0, 10.0, 90.0, 60.0)]
    with pytest.raises(UserError, match=r"different sizes \(100x50, 80x50\).*--size W,H, e.g. --size 100,50"):
        rec.output_size(mixed, None, None)
    with pytest.raises(UserError, match=r"--size 64: the images have different aspect ratios.*--size W,H"):
        rec.output_size(mixed, 64, None)
    assert rec.output_size(mixed, (64, 32), None) == (64, 32)
    with pytest.raises(UserError, match="--size 'big'"):
        parse_size("big")
    crops = parse_crops(["0,0,10,20", "b=1,2,3,4"], ["a", "b"])
    assert crops == {"a": (0.0, 0.0, 10.0, 20.0), "b": (1.0, 2.0, 3.0, 4.0)}
    with pytest.raises(UserError, match="unknown camera 'c'"):
        parse_crops(["c=0,0,1,1"], ["a", "b"])
    with pytest.raises(UserError, match="x1 > x0"):
        parse_crops(["5,0,1,1"], ["a"])
    with pytest.raises(UserError, match="expected CAMERA=FILE"):
        camera_pairs(["a.mp4"], "--videos")


def test_split_frames():
    splits = rec.split_frames(np.array([1, 3, 5, 7, 9]), np.arange(12), "2", 2, seed=0, stride=1)
    values = list(splits.values())
    assert values.count("labelled") == 2 and values.count("test") == 2 and values.count("unlabelled") == 8
    assert all(splits[f] == "unlabelled" for f in (0, 2, 4, 6, 8, 10, 11))
    every = rec.split_frames(np.array([1, 3, 5]), np.arange(6), "all", 1, seed=0, stride=1)
    assert sorted(f for f, v in every.items() if v != "unlabelled") == [1, 3, 5]
    assert list(every.values()).count("test") == 1
    with pytest.raises(ValueError, match="--test 6: only 5 frames"):
        rec.split_frames(np.array([1, 3, 5, 7, 9]), np.arange(12), "2", 6, 0, 1)


def test_every_label_format_has_its_option_and_is_built_from_the_options_it_takes():
    """s3k import builds a label format from the registry: every registered format has the option that names
    its files, and build() passes a format the options it takes and no other."""
    from s3k.cli.import_ import LABEL_OPTIONS
    from s3k.data import import_labels as fmt

    assert set(LABEL_OPTIONS) == set(fmt.LABEL_FORMATS)
    options = dict(track="a", accept_predictions=True, frame_ids_from="row", min_score=0.2, camera_map=None)
    assert fmt.build("deeplabcut", {"c": "c.csv"}, **options) == fmt.DeepLabCut({"c": "c.csv"}, "row")
    assert fmt.build("openpose", {"c": "d"}, **options) == fmt.OpenPose({"c": "d"}, 0.2)
    assert fmt.build("sleap-project", "p.slp", **options) == fmt.SleapProject("p.slp", "a", None, True)
    assert fmt.build("deepfly3d", "x.pkl", **options) == fmt.DeepFly3D("x.pkl")
    with pytest.raises(UserError, match="no label format 'nope'"):
        fmt.build("nope", "x")
