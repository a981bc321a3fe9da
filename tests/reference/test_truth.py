"""pipeline.reference.truth: every reader of true cameras, and every malformed file as one line naming it."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.io as sio

from pipeline.core import so3
from pipeline.core.errors import InputFileError
from pipeline.io.rotations import write_rotations
from pipeline.reference.truth import read_cameras_file, read_reference, write_cameras_file


def _l1_fixture(tmp_path, n: int = 5):
    rng = np.random.default_rng(1)
    R = so3.random_rotations(n, rng)
    # Edges in both orientations, 1-based: RR[:, :, k] = R_b R_aᵀ for (a, b) = I[:, k].
    pairs = np.array([(0, 1), (2, 1), (2, 3), (4, 3), (0, 4)])
    RR = R[pairs[:, 1]] @ np.swapaxes(R[pairs[:, 0]], 1, 2)
    Rgt = R.copy()
    Rgt[3] = 0.0  # no ground truth for camera 3
    path = tmp_path / "l1.mat"
    sio.savemat(path, {"RR": np.moveaxis(RR, 0, 2), "I": (pairs.T + 1).astype(float), "Rgt": np.moveaxis(Rgt, 0, 2)})
    return path, R


def test_cameras_file_round_trip(tmp_path) -> None:
    rng = np.random.default_rng(6)
    R = so3.random_rotations(3, rng)
    t = rng.normal(size=(3, 3))
    K = np.array([[800.0, 0, 320], [0, 810.0, 240], [0, 0, 1]])
    p = write_cameras_file(tmp_path / "cameras.txt", ["a.png", "b.png", "c.png"], K, R, t)
    for ref in (read_cameras_file(p), read_reference(p)):
        assert ref.source == "cameras" and ref.names == ["a.png", "b.png", "c.png"]
        np.testing.assert_allclose(ref.R, R, atol=1e-15)
        np.testing.assert_allclose(ref.K, np.broadcast_to(K, (3, 3, 3)))
        # x_cam = R X + t vanishes at the centre.
        np.testing.assert_allclose(np.einsum("nab,nb->na", R, ref.centers) + t, 0.0, atol=1e-12)


@pytest.mark.parametrize(
    "content, match",
    [
        ("a 1 1 0 0 1 0 0 0 1 0 0 0 1 0 0\n", r":1: expected 'name fx fy cx cy r11 \.\.\. r33 t1 t2 t3' \(17 fields\), got 16"),
        ("a 1 1 0 0 1 0 0 0 1 0 0 0 1 0 0 zz\n", r":1: every field after the name must be a number"),
        ("a 1 1 0 0 1 0 0 0 1 0 0 0 -1 0 0 0\n", r"R of camera 'a' is not a rotation"),
        ("a 1 1 0 0 1 0 0 0 1 0 0 0 1 0 0 0\na 1 1 0 0 1 0 0 0 1 0 0 0 1 0 0 0\n", r"camera names repeat"),
        ("# nothing\n", r"holds no cameras"),
    ],
)
def test_cameras_file_malformed(tmp_path, content: str, match: str) -> None:
    p = tmp_path / "cams.txt"
    p.write_text(content)
    with pytest.raises(InputFileError, match=match):
        read_cameras_file(p)


def test_read_reference_dispatch_and_errors(tmp_path) -> None:
    R = so3.random_rotations(2, np.random.default_rng(7))
    ref = read_reference(write_rotations(tmp_path / "rot.txt", ["x", "y"], R))
    assert ref.source == "rotations" and ref.names == ["x", "y"]
    np.testing.assert_allclose(ref.R, R, atol=1e-15)
    path, R5 = _l1_fixture(tmp_path)
    ref = read_reference(path)
    assert ref.source == "mat" and ref.names == ["0", "1", "2", "4"]  # camera 3 has no ground truth
    np.testing.assert_allclose(ref.R, R5[[0, 1, 2, 4]], atol=1e-15)
    with pytest.raises(InputFileError, match="does not exist"):
        read_reference(tmp_path / "missing.txt")
    (tmp_path / "odd.txt").write_text("a 1 2 3\n")
    with pytest.raises(InputFileError, match="unrecognised reference with 4 fields"):
        read_reference(tmp_path / "odd.txt")
    (tmp_path / "empty_dir").mkdir()
    with pytest.raises(InputFileError, match="neither a COLMAP model"):
        read_reference(tmp_path / "empty_dir")
    (tmp_path / "bin.dat").write_bytes(bytes(range(128, 256)))
    with pytest.raises(InputFileError, match="not a text file"):
        read_reference(tmp_path / "bin.dat")
    nogt = tmp_path / "nogt.mat"
    sio.savemat(nogt, {"RR": R[0][:, :, None], "I": np.array([[1.0], [2.0]])})
    with pytest.raises(InputFileError, match="no ground truth"):
        read_reference(nogt)


def test_colmap_model_reference(tmp_path) -> None:
    import pycolmap

    R = so3.random_rotations(3, np.random.default_rng(8))
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId.SIMPLE_PINHOLE, 500.0, 640, 480))
    for k in range(3):
        image = pycolmap.Image(name=f"img{k}.jpg", camera_id=1, image_id=k + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(R[k]), np.array([0.0, 0.0, k + 1.0])))
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    rec.write(str(model))
    assert read_reference(tmp_path / "sparse").names == ["img0.jpg", "img1.jpg", "img2.jpg"]  # COLMAP's sparse/0 layout
    ref = read_reference(model)
    assert ref.source == "colmap" and ref.names == ["img0.jpg", "img1.jpg", "img2.jpg"]
    np.testing.assert_allclose(ref.R, R, atol=1e-12)
    np.testing.assert_allclose(ref.K[0], [[500, 0, 320], [0, 500, 240], [0, 0, 1]])
    np.testing.assert_allclose(np.einsum("nab,nb->na", R, ref.centers)[:, 2], -np.arange(1.0, 4.0), atol=1e-12)
    (model / "images.bin").write_bytes(b"broken")
    with pytest.raises(InputFileError, match="pycolmap cannot read|too short for a COLMAP binary file"):
        read_reference(model)


@pytest.mark.data
def test_strecha_reference(shared_data, tmp_path) -> None:
    root = shared_data / "strecha" / "fountain-P11"
    ref = read_reference(root)
    assert ref.source == "strecha" and len(ref.names) == 11 and ref.names[0] == "0000.jpg"
    raw = np.loadtxt(root / "gt_dense_cameras" / "0000.jpg.camera", max_rows=8)
    np.testing.assert_allclose(ref.R[0], raw[4:7].T, atol=1e-5)  # file R is world_from_cam
    assert read_reference(root / "gt_dense_cameras").names == ref.names
    # Physical check of the convention: optical axes of neighbouring cameras meet in
    # front of both cameras (the fountain), which fails for the transposed reading.
    z = ref.R[:, 2, :]  # viewing direction in world = third row of cam_from_world
    C = ref.centers
    depths = []
    for a in range(10):
        A = np.stack([z[a], -z[a + 1]], axis=1)
        s = np.linalg.lstsq(A, C[a + 1] - C[a], rcond=None)[0]
        depths.append(s)
    assert np.all(np.array(depths) > 0)
    bad = tmp_path / "gt_dense_cameras"
    bad.mkdir()
    (bad / "0000.jpg.camera").write_text("1 2 3\n")
    with pytest.raises(InputFileError, match="expected 26 numbers"):
        read_reference(tmp_path)


@pytest.mark.data
def test_middlebury_reference(shared_data) -> None:
    ref = read_reference(shared_data / "middlebury-templeSparseRing" / "templeSR_par.txt")
    assert ref.source == "middlebury" and len(ref.names) == 16 and ref.names[0] == "templeSR0001.png"
    # R is cam_from_world: the centre of the object's bounding box (README.txt)
    # projects inside every 640×480 image, in front of the camera.
    X = 0.5 * (np.array([-0.073568, 0.021728, -0.012445]) + np.array([0.028855, 0.181892, 0.062736]))
    x_cam = np.einsum("nab,nb->na", ref.R, X - ref.centers)
    assert np.all(x_cam[:, 2] > 0)
    uv = np.einsum("nab,nb->na", ref.K, x_cam)
    uv = uv[:, :2] / uv[:, 2:]
    assert np.all((uv > 0) & (uv < [640, 480]))


# ------------------------------------------------------------------ bad input: one line naming the file
def _strecha_file(K: np.ndarray | None = None) -> str:
    K = np.array([[2759.48, 0, 1520.69], [0, 2764.16, 1006.81], [0, 0, 1]]) if K is None else K
    R = so3.random_rotations(1, np.random.default_rng(3))[0]
    rows = [K, np.zeros((1, 3)), R.T, np.array([[1.0, 2.0, 3.0]]), np.array([[3072.0, 2048.0]])]
    return "\n".join(" ".join(f"{v:.17g}" for v in r) for block in rows for r in np.atleast_2d(block)) + "\n"


def _one_line(exc: pytest.ExceptionInfo, path) -> None:
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg, msg


def test_strecha_K_with_nan_or_zero_focal_is_refused(tmp_path) -> None:
    folder = tmp_path / "gt_dense_cameras"
    folder.mkdir()
    (folder / "0000.jpg.camera").write_text(_strecha_file())
    assert read_reference(tmp_path).names == ["0000.jpg"]
    bad = _strecha_file().replace("2759.48", "nan", 1)
    (folder / "0001.jpg.camera").write_text(bad)
    with pytest.raises(InputFileError, match="NaN or inf") as exc:
        read_reference(tmp_path)
    _one_line(exc, folder / "0001.jpg.camera")
    (folder / "0001.jpg.camera").write_text(_strecha_file().replace("2759.48", "0", 1))
    with pytest.raises(InputFileError, match="not a pinhole K") as exc:
        read_reference(folder)
    _one_line(exc, folder / "0001.jpg.camera")
    (folder / "0001.jpg.camera").write_bytes(b"\xff\xfe" + _strecha_file().encode())
    with pytest.raises(InputFileError, match="not UTF-8") as exc:
        read_reference(folder)
    _one_line(exc, folder / "0001.jpg.camera")


@pytest.mark.parametrize("reader", [read_cameras_file, read_reference])
def test_cameras_file_with_zero_focal_or_non_utf8_is_refused(tmp_path, reader) -> None:
    R = so3.random_rotations(2, np.random.default_rng(4))
    K = np.array([[0.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    p = write_cameras_file(tmp_path / "cameras.txt", ["a.png", "b.png"], K, R, np.zeros((2, 3)))
    with pytest.raises(InputFileError, match="not a pinhole K") as exc:
        reader(p)
    _one_line(exc, p)
    good = write_cameras_file(tmp_path / "good.txt", ["a.png", "b.png"], np.diag([500.0, 500.0, 1.0]), R,
                              np.zeros((2, 3))).read_bytes()
    p.write_bytes(good + "c.png \xe9\n".encode("latin-1"))  # valid first lines, then a byte that is not UTF-8
    with pytest.raises(InputFileError, match="not UTF-8") as exc:
        reader(p)
    _one_line(exc, p)


def test_middlebury_malformed(tmp_path) -> None:
    row = "a.png 500 0 320 0 500 240 0 0 1 1 0 0 0 1 0 0 0 1 0 0 1\n"
    p = tmp_path / "x_par.txt"
    p.write_text("2\n" + row + row.replace("a.png", "b.png"))
    assert read_reference(p).source == "middlebury"
    for content, match in [("2\n" + row + row.replace(" 1\n", "\n"), r":3: expected 'imgname k11"),
                           ("1\n" + row.replace("500", "nan", 1), "NaN or inf"),
                           ("1\n" + row.replace(" 0 0 1 1", " 0 0 2 1", 1), "not a pinhole K")]:
        p.write_text(content)
        with pytest.raises(InputFileError, match=match) as exc:
            read_reference(p)
        _one_line(exc, p)


def _mutations(data: bytes, rng: np.random.Generator, n: int):
    """``n`` seeded mutations of ``data``: byte flips, cuts, insertions, swapped tokens, duplicated lines."""
    tokens = [b"nan", b"inf", b"-inf", b"0", b"-1", b"1e400", b"abc", b"", b"\xff", b"#", b"1 2", b"\x00"]
    for _ in range(n):
        b = bytearray(data)
        kind = rng.integers(6)
        k = int(rng.integers(len(b)))
        if kind == 0:
            b[k] = int(rng.integers(256))
        elif kind == 1:
            del b[k:k + int(rng.integers(1, 40))]
        elif kind == 2:
            b[k:k] = bytes(rng.integers(0, 256, int(rng.integers(1, 8))).astype(np.uint8))
        elif kind == 3:
            words = bytes(b).split(b" ")
            w = int(rng.integers(len(words)))
            words[w] = tokens[int(rng.integers(len(tokens)))]
            b = bytearray(b" ".join(words))
        elif kind == 4:
            lines = bytes(b).split(b"\n")
            lines.insert(int(rng.integers(len(lines))), lines[int(rng.integers(len(lines)))])
            b = bytearray(b"\n".join(lines))
        else:
            b = b[:k]
        yield bytes(b)


def _check_accepted(ref) -> None:
    assert len(ref.names) == len(set(ref.names)) > 0
    assert np.all(so3.is_rotation(ref.R, 1e-9))
    if ref.K is not None:
        assert np.all(np.isfinite(ref.K)) and np.all(ref.K[..., 0, 0] > 0) and np.all(ref.K[..., 1, 1] > 0)
    if ref.centers is not None:
        assert np.all(np.isfinite(ref.centers))


@pytest.mark.parametrize("layout", ["rotations", "cameras", "middlebury", "strecha"])
def test_fuzzed_reference_files_give_one_line_errors(tmp_path, layout) -> None:
    """300 mutations of each text layout: a valid Reference or one InputFileError line naming the file."""
    rng = np.random.default_rng({"rotations": 1, "cameras": 2, "middlebury": 3, "strecha": 4}[layout])
    R = so3.random_rotations(3, rng)
    names = ["a.png", "b.png", "c.png"]
    K = np.array([[500.0, 0, 320], [0, 510.0, 240], [0, 0, 1]])
    if layout == "rotations":
        path = write_rotations(tmp_path / "rot.txt", names, R)
    elif layout == "cameras":
        path = write_cameras_file(tmp_path / "cams.txt", names, K, R, rng.normal(size=(3, 3)))
    elif layout == "middlebury":
        path = tmp_path / "x_par.txt"
        path.write_text("3\n" + "".join(f"{n} " + " ".join(f"{v:.17g}" for v in [*K.ravel(), *R[k].ravel(), 0, 0, 1])
                                        + "\n" for k, n in enumerate(names)))
    else:
        (tmp_path / "gt_dense_cameras").mkdir()
        path = tmp_path / "gt_dense_cameras" / "0000.jpg.camera"
        path.write_text(_strecha_file())
    original = path.read_bytes()
    accepted = 0
    for data in _mutations(original, rng, 300):
        path.write_bytes(data)
        try:
            ref = read_reference(path if layout != "strecha" else path.parent)
        except InputFileError as exc:
            assert "\n" not in str(exc) and str(path) in str(exc), str(exc)
            continue
        _check_accepted(ref)
        accepted += 1
    assert accepted < 300  # the mutations do break files


def _colmap_model(folder) -> np.ndarray:
    """A 3-image COLMAP model in ``folder``; returns its cam_from_world rotations."""
    import pycolmap

    R = so3.random_rotations(3, np.random.default_rng(8))
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId.SIMPLE_PINHOLE, 500.0, 640, 480))
    for k in range(3):
        image = pycolmap.Image(name=f"img{k}.jpg", camera_id=1, image_id=k + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(R[k]), np.array([0.0, 0.0, k + 1.0])))
    folder.mkdir(parents=True)
    rec.write(str(folder))
    return R


@pytest.mark.slow
@pytest.mark.parametrize("name", ["images.bin", "frames.bin", "points3D.bin", "cameras.bin"])
def test_damaged_colmap_model_gives_one_line_not_a_hang(tmp_path, monkeypatch, name) -> None:
    """pycolmap's own readers hang on a truncated images.bin or frames.bin and allocate gigabytes on a
    damaged points3D.bin; the model is read in a child process with a time and memory limit."""
    from pipeline.reference import truth

    monkeypatch.setattr(truth, "COLMAP_TIMEOUT_S", 8.0)
    model = tmp_path / "model"
    R = _colmap_model(model)
    data = (model / name).read_bytes()
    rng = np.random.default_rng(len(name))
    cuts = sorted({int(k) for k in rng.integers(1, len(data), 2)})
    for k in cuts:
        (model / name).write_bytes(data[:k])
        try:
            ref = read_reference(model)
        except InputFileError as exc:
            assert "\n" not in str(exc) and str(model) in str(exc), str(exc)
        else:  # a cut the reader survives must not read as another model
            assert list(ref.names) == [f"img{m}.jpg" for m in range(3)], ref.names
            np.testing.assert_allclose(ref.R, R, atol=1e-9)
