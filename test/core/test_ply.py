"""Splat file I/O: 3DGS .ply round trip and layout, foreign/ASCII/point-cloud PLYs, .splat."""

from pathlib import Path

import numpy as np
import pytest
import torch

from soma_ros.core.geometry import quat_normalize, quat_to_rotmat
from soma_ros.core.ply import PlyError, load_splats, read_ply, read_splat, write_ply, write_splat
from soma_ros.core.splats import SH_C0, Splats

torch.set_num_threads(1)

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "real_rope_4view"


def random_splats(n=50, k_rest=15, n_attr=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    return Splats(
        means=torch.randn(n, 3, generator=g),
        quats=quat_normalize(torch.randn(n, 4, generator=g)),
        scales=torch.exp(torch.randn(n, 3, generator=g) - 4),
        opacities=torch.rand(n, generator=g) * 0.98 + 0.01,
        sh_dc=torch.randn(n, 3, generator=g),
        sh_rest=torch.randn(n, k_rest, 3, generator=g) * 0.1,
        mass=torch.rand(n, generator=g) * 1e-3,
        attrs=torch.randn(n, n_attr, generator=g),
    )


def _header(path):
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    return raw[:end].decode().splitlines(), raw[end:]


def test_ply_round_trip_all_fields(tmp_path):
    sp = random_splats()
    p = tmp_path / "a.ply"
    write_ply(p, sp)
    back = read_ply(p)
    assert len(back) == len(sp)
    # stored verbatim as float32: identical
    for name in ("means", "sh_dc", "sh_rest", "mass", "attrs"):
        assert torch.equal(getattr(back, name), getattr(sp, name)), name
    # stored through log / logit / normalisation: float32 rounding only
    torch.testing.assert_close(back.scales, sp.scales, rtol=3e-7, atol=0)
    torch.testing.assert_close(back.opacities, sp.opacities, rtol=0, atol=2e-7)
    torch.testing.assert_close(back.quats, sp.quats, rtol=0, atol=3e-7)
    # float64 files are read to float64 splats the same way
    back64 = read_ply(p, dtype=torch.float64)
    assert back64.means.dtype == torch.float64 and torch.equal(back64.means.float(), sp.means)


def test_ply_layout_is_standard_3dgs(tmp_path):
    n, k = 4, 3
    sp = random_splats(n=n, k_rest=k, n_attr=2)
    sp.sh_rest = torch.arange(n * k * 3, dtype=torch.float32).reshape(n, k, 3)
    p = tmp_path / "layout.ply"
    write_ply(p, sp)
    lines, body = _header(p)
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    props = [ln.split()[2] for ln in lines if ln.startswith("property")]
    assert all(ln.split()[1] == "float" for ln in lines if ln.startswith("property"))
    expect = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
              + [f"f_rest_{i}" for i in range(3 * k)]
              + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
                 "mass", "attr_0", "attr_1"])
    assert props == expect
    arr = np.frombuffer(body, dtype=np.dtype([(q, "<f4") for q in props]))
    # f_rest is channel-major: f_rest_{c*K + k} = sh_rest[:, k, c]
    for c in range(3):
        for kk in range(k):
            np.testing.assert_array_equal(arr[f"f_rest_{c * k + kk}"], sp.sh_rest[:, kk, c].numpy())
    o = sp.opacities.double().numpy()
    np.testing.assert_allclose(arr["opacity"], np.log(o / (1 - o)), rtol=1e-6)
    np.testing.assert_allclose(arr["scale_1"], np.log(sp.scales[:, 1].double().numpy()), rtol=1e-6)
    np.testing.assert_array_equal(arr["rot_0"], sp.quats[:, 0].numpy())  # w first
    # without extras: exactly the 3DGS property set
    write_ply(tmp_path / "plain.ply", sp, extras=False)
    props2 = [ln.split()[2] for ln in _header(tmp_path / "plain.ply")[0] if ln.startswith("property")]
    assert props2 == expect[:-3]


def _write_foreign_ply(path, fields: dict, fmt="binary_little_endian", types=None, extra_elements=""):
    names = list(fields)
    n = len(next(iter(fields.values())))
    types = types or {}
    tmap = {"f4": "float", "f8": "double", "u1": "uchar", "i4": "int"}
    lines = ["ply", f"format {fmt} 1.0", "comment made by a foreign tool", f"element vertex {n}"]
    lines += [f"property {tmap[types.get(k, 'f4')]} {k}" for k in names]
    lines += [extra_elements] if extra_elements else []
    lines.append("end_header")
    head = ("\n".join(lines) + "\n").encode()
    if fmt == "ascii":
        rows = [" ".join(str(fields[k][i]) for k in names) for i in range(n)]
        Path(path).write_bytes(head + ("\n".join(rows) + "\n").encode())
        return
    e = "<" if fmt == "binary_little_endian" else ">"
    arr = np.empty(n, dtype=np.dtype([(k, e + types.get(k, "f4")) for k in names]))
    for k in names:
        arr[k] = fields[k]
    Path(path).write_bytes(head + arr.tobytes())


def test_foreign_3dgs_ply_big_endian_without_extras(tmp_path):
    n = 6
    rng = np.random.default_rng(0)
    q = rng.standard_normal((n, 4)) * 3  # unnormalised, as 3DGS training leaves them
    f = {"x": rng.standard_normal(n), "y": rng.standard_normal(n), "z": rng.standard_normal(n),
         "nx": np.zeros(n), "ny": np.zeros(n), "nz": np.zeros(n),
         "f_dc_0": rng.standard_normal(n), "f_dc_1": rng.standard_normal(n), "f_dc_2": rng.standard_normal(n),
         "opacity": rng.standard_normal(n) * 3,
         "scale_0": rng.standard_normal(n) - 5, "scale_1": rng.standard_normal(n) - 5,
         "scale_2": rng.standard_normal(n) - 5,
         "rot_0": q[:, 0], "rot_1": q[:, 1], "rot_2": q[:, 2], "rot_3": q[:, 3],
         "semantic_id": np.arange(n)}
    p = tmp_path / "foreign.ply"
    _write_foreign_ply(p, f, fmt="binary_big_endian", types={"x": "f8", "semantic_id": "i4"})
    sp = read_ply(p)
    np.testing.assert_allclose(sp.means[:, 0].numpy(), f["x"], rtol=1e-6)
    np.testing.assert_allclose(sp.opacities.numpy(), 1 / (1 + np.exp(-f["opacity"])), rtol=1e-6)
    np.testing.assert_allclose(sp.scales[:, 2].numpy(), np.exp(f["scale_2"]), rtol=1e-6)
    np.testing.assert_allclose(sp.quats.numpy(), q / np.linalg.norm(q, axis=1, keepdims=True), atol=1e-6)
    assert sp.sh_rest.shape == (n, 0, 3) and sp.attrs.shape == (n, 0)
    torch.testing.assert_close(sp.mass, torch.full((n,), 1.0 / n))  # default uniform mass
    # faces after the vertices are skipped
    p2 = tmp_path / "with_faces.ply"
    _write_foreign_ply(p2, f, extra_elements="element face 0\nproperty list uchar int vertex_indices")
    assert len(read_ply(p2)) == n


def test_missing_properties_are_named(tmp_path):
    n = 3
    f = {k: np.zeros(n) for k in ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                                  "scale_0", "scale_1", "rot_0", "rot_1", "rot_2"]}
    p = tmp_path / "broken.ply"
    _write_foreign_ply(p, f)
    with pytest.raises(PlyError, match=r"\['scale_2', 'rot_3'\]"):
        read_ply(p)
    _write_foreign_ply(p, {"x": np.zeros(2), "y": np.zeros(2)})
    with pytest.raises(PlyError, match=r"\['z'\]"):
        read_ply(p)
    (tmp_path / "junk.ply").write_bytes(b"not a ply at all\n")
    with pytest.raises(PlyError, match="not a PLY"):
        read_ply(tmp_path / "junk.ply")
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\n"
                  b"property float y\nproperty float z\nend_header\n" + b"\0" * 20)
    with pytest.raises(PlyError, match="truncated"):
        read_ply(p)
    with pytest.raises(PlyError, match="extension"):
        (tmp_path / "a.xyz").write_text("1 2 3")
        load_splats(tmp_path / "a.xyz")
    with pytest.raises(FileNotFoundError):
        load_splats(tmp_path / "missing.ply")


def test_ascii_point_cloud_ply(tmp_path):
    pts = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.02, 0.0], [0.03, 0.03, 0.01]])
    cols = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]], dtype=np.uint8)
    p = tmp_path / "cloud.ply"
    _write_foreign_ply(p, {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "red": cols[:, 0],
                           "green": cols[:, 1], "blue": cols[:, 2]}, fmt="ascii",
                       types={"red": "u1", "green": "u1", "blue": "u1"})
    sp = read_ply(p)
    np.testing.assert_allclose(sp.means.numpy(), pts, atol=1e-7)
    np.testing.assert_allclose(sp.colors().numpy(), cols / 255.0, atol=1e-6)
    # isotropic, scale = median nearest-neighbour distance: median(0.01, 0.01, 0.02, 0.0332) = 0.015
    assert torch.all(sp.scales == sp.scales[0, 0])
    assert sp.scales[0, 0].item() == pytest.approx(0.015, rel=1e-5)
    assert read_ply(p, point_scale=0.003).scales[0, 0].item() == pytest.approx(0.003)


@pytest.mark.skipif(not (DATA / "pcd.ply").exists(), reason="shared rope data not present")
def test_real_point_cloud_ply():
    sp = load_splats(DATA / "pcd.ply")  # Open3D binary: double xyz, uchar rgb
    assert len(sp) == 3491
    sp.validate()
    c = sp.colors()
    assert (c.mean(0)[0] > c.mean(0)[2]).item()  # a brown rope: more red than blue


def test_splat_round_trip_within_quantisation(tmp_path):
    sp = random_splats(n=200, k_rest=0, n_attr=0, seed=3)
    sp.sh_dc = (torch.rand(200, 3) - 0.5) / SH_C0  # colours inside [0, 1]
    p = tmp_path / "a.splat"
    write_splat(p, sp)
    assert p.stat().st_size == 32 * 200
    back = load_splats(p)
    assert torch.equal(back.means, sp.means) and torch.equal(back.scales, sp.scales)
    assert (back.colors() - sp.colors()).abs().max() <= 0.5 / 255 + 1e-6
    assert (back.opacities - sp.opacities).abs().max() <= 0.5 / 255 + 1e-6
    # rotation: 8-bit components, compare rotation matrices
    dR = (quat_to_rotmat(back.quats) - quat_to_rotmat(sp.quats)).abs().max()
    assert dR < 0.03
    # second round trip: position, scale, colour and opacity bytes are unchanged; the
    # rotation bytes move by at most 1 (read_splat renormalises the decoded quaternion)
    write_splat(tmp_path / "b.splat", back)
    b1 = np.frombuffer(p.read_bytes(), np.uint8).reshape(-1, 32)
    b2 = np.frombuffer((tmp_path / "b.splat").read_bytes(), np.uint8).reshape(-1, 32)
    assert np.array_equal(b1[:, :28], b2[:, :28])
    assert np.abs(b1[:, 28:].astype(int) - b2[:, 28:].astype(int)).max() <= 1
    (tmp_path / "bad.splat").write_bytes(b"\0" * 33)
    with pytest.raises(PlyError, match="multiple of 32"):
        read_splat(tmp_path / "bad.splat")


@pytest.mark.skipif(not (DATA / "gs_orig.splat").exists(), reason="shared rope data not present")
def test_real_splat_file_to_ply(tmp_path):
    sp = read_splat(DATA / "gs_orig.splat")
    assert len(sp) == 8957
    sp.validate()
    write_ply(tmp_path / "rope.ply", sp)
    back = read_ply(tmp_path / "rope.ply")
    assert torch.equal(back.means, sp.means)
    torch.testing.assert_close(back.opacities, sp.opacities.clamp(1e-7, 1 - 1e-7), rtol=0, atol=2e-7)


def test_ply_file_read_and_written_again_is_byte_identical(tmp_path):
    """write -> read -> write reproduces the file exactly (every stored property), for
    a realistic scene and for random splats once their quaternions are normalised."""
    from soma_ros.core.scenes import synthetic_rope

    sp = random_splats()
    sp.quats = sp.quats / sp.quats.norm(dim=-1, keepdim=True)
    for i, s in enumerate((synthetic_rope(3000, seed=2), sp)):
        a, b = tmp_path / f"a{i}.ply", tmp_path / f"b{i}.ply"
        write_ply(a, s)
        write_ply(b, read_ply(a))
        assert a.read_bytes() == b.read_bytes()


# --------------------------------------------------------------------------- graphdeco / SIBR compatibility
def _graphdeco_style_load(path, max_sh_degree):
    """What a loader in the graphdeco layout does with a .ply (written for this test from the
    layout's description): plyfile, xyz, opacity, f_dc, f_rest_* sorted by index and required to
    number 3 * ((D + 1)^2 - 1), scale_* and rot_* sorted by index; returns the arrays."""
    import plyfile

    el = plyfile.PlyData.read(str(path)).elements[0]
    names = [p.name for p in el.properties]
    xyz = np.stack([np.asarray(el[k]) for k in "xyz"], axis=1)
    opacity = np.asarray(el["opacity"])[:, None]
    dc = np.stack([np.asarray(el[f"f_dc_{i}"]) for i in range(3)], axis=1)
    rest_names = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n.split("_")[-1]))
    assert len(rest_names) == 3 * (max_sh_degree + 1) ** 2 - 3
    rest = np.stack([np.asarray(el[n]) for n in rest_names], axis=1) if rest_names else np.zeros((len(xyz), 0))
    rest = rest.reshape(len(xyz), 3, (max_sh_degree + 1) ** 2 - 1)
    scale = np.stack([np.asarray(el[n]) for n in sorted((n for n in names if n.startswith("scale_")),
                                                           key=lambda n: int(n.split("_")[-1]))], axis=1)
    rot = np.stack([np.asarray(el[n]) for n in sorted((n for n in names if n.startswith("rot")),
                                                         key=lambda n: int(n.split("_")[-1]))], axis=1)
    return xyz, opacity, dc, rest, scale, rot


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_plyfile_and_a_graphdeco_layout_loader_read_the_written_ply(tmp_path, degree):
    """Written at SH degree 0-3 (padding or cutting the higher bands), the file is what plyfile
    and a graphdeco-layout loader read: counts, f_rest channel-major, log scales, logit opacity.
    The header is SIBR's: format on line 2, element vertex N on line 3, no comment."""
    import plyfile

    sp = random_splats(n=40, k_rest=8, n_attr=0)  # degree 2 in memory
    p = tmp_path / f"d{degree}.ply"
    write_ply(p, sp, extras=False, sh_degree=degree)
    lines, _ = _header(p)
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 40"]
    assert not any(ln.startswith("comment") for ln in lines)
    ply = plyfile.PlyData.read(str(p))
    assert [e.name for e in ply.elements] == ["vertex"] and ply["vertex"].count == 40
    assert all(prop.val_dtype == "f4" for prop in ply["vertex"].properties)
    xyz, opacity, dc, rest, scale, rot = _graphdeco_style_load(p, degree)
    k = (degree + 1) ** 2 - 1
    np.testing.assert_array_equal(xyz, sp.means.numpy())
    np.testing.assert_array_equal(dc, sp.sh_dc.numpy())
    want = np.zeros((40, k, 3), np.float32)
    m = min(k, 8)
    want[:, :m] = sp.sh_rest[:, :m].numpy()
    np.testing.assert_array_equal(rest, want.transpose(0, 2, 1))  # [N, 3, K]: graphdeco's features_rest layout
    np.testing.assert_allclose(np.exp(scale), sp.scales.numpy(), rtol=1e-6)
    np.testing.assert_allclose(1 / (1 + np.exp(-opacity[:, 0])), sp.opacities.numpy(), atol=1e-6)
    np.testing.assert_array_equal(rot, sp.quats.numpy())
    back = read_ply(p)  # and it reads back here at that degree
    assert back.sh_rest.shape == (40, k, 3)
    np.testing.assert_array_equal(back.sh_rest.numpy(), want)


def test_bad_sh_degree_and_integer_3dgs_properties_are_refused(tmp_path):
    sp = random_splats(n=5, k_rest=3, n_attr=0)
    with pytest.raises(ValueError, match="sh_degree must be 0..3"):
        write_ply(tmp_path / "x.ply", sp, sh_degree=4)
    with pytest.raises(ValueError, match="no SH degree 0-3"):
        write_ply(tmp_path / "x.ply", random_splats(n=5, k_rest=5, n_attr=0))
    f = {k: np.zeros(3) for k in ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
                                  "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]}
    _write_foreign_ply(tmp_path / "ints.ply", f, types={"scale_0": "u1", "opacity": "i4"})
    with pytest.raises(PlyError, match=r"must be float or double, not integers: \['opacity', 'scale_0'\]"):
        read_ply(tmp_path / "ints.ply")


def test_headers_are_checked_against_the_limit_and_the_file_length_before_reading(tmp_path):
    """A header's counts are checked before any data is read: against max_splats, against the
    bytes a binary file really holds (short or long), and against what an ASCII file can hold."""
    from soma_ros.core.ply import read_ply_header

    p = tmp_path / "a.ply"
    write_ply(p, random_splats(n=30, k_rest=0, n_attr=0), extras=False)
    assert read_ply_header(p).vertex_count == 30
    with pytest.raises(PlyError, match="announces 30 vertices, more than the limit of 29"):
        read_ply(p, max_splats=29)
    raw = p.read_bytes()
    (tmp_path / "long.ply").write_bytes(raw + b"\0" * 7)
    with pytest.raises(PlyError, match="does not match its header"):
        read_ply(tmp_path / "long.ply")
    head = b"ply\nformat ascii 1.0\nelement vertex 100000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    (tmp_path / "lie.ply").write_bytes(head + b"0 0 0\n" * 40)
    with pytest.raises(PlyError, match="truncated PLY: the header announces 300000000 ASCII values"):
        read_ply(tmp_path / "lie.ply")
    (tmp_path / "nohead.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\n" + b"comment x\n" * 8000)
    with pytest.raises(PlyError, match="no end_header within 65536 bytes"):
        read_ply(tmp_path / "nohead.ply")
    (tmp_path / "dup.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float x\n"
                                       b"end_header\n1 2\n")
    with pytest.raises(PlyError, match="declares a property twice"):
        read_ply(tmp_path / "dup.ply")
    (tmp_path / "n.splat").write_bytes(b"\0" * 64)
    with pytest.raises(PlyError, match="holds 2 splats, more than the limit of 1"):
        read_splat(tmp_path / "n.splat", max_splats=1)


def test_soma_scene_info_convert_and_export(tmp_path, capsys):
    """`soma scene export` writes a bundle's splats in the standard layout (no extras), `convert`
    moves between .ply degrees and .splat, `info` describes each; bad input is one line."""
    from soma_ros.cli import main
    from soma_ros.core.scenes import synthetic_bundle

    bundle = synthetic_bundle(300, width=32, height=24).save(tmp_path / "run" / "scene")
    assert main(["scene", "export", str(tmp_path / "run"), str(tmp_path / "std.ply"), "--sh-degree", "3"]) == 0
    props = [ln.split()[2] for ln in _header(tmp_path / "std.ply")[0] if ln.startswith("property")]
    assert len(props) == 62 and "mass" not in props  # graphdeco's SH-degree-3 record exactly
    assert main(["scene", "convert", str(tmp_path / "std.ply"), str(tmp_path / "a.splat")]) == 0
    assert main(["scene", "convert", str(tmp_path / "a.splat"), str(tmp_path / "b.ply")]) == 0
    capsys.readouterr()
    assert main(["scene", "info", str(tmp_path / "b.ply")]) == 0
    out = capsys.readouterr().out
    assert "300 splats" in out and "SH degree 0" in out and "binary_little_endian" in out
    assert main(["scene", "info", str(bundle)]) == 0 and "300 splats" in capsys.readouterr().out
    back = read_ply(tmp_path / "b.ply")
    assert torch.equal(back.means, read_ply(bundle / "splats.ply").means)
    assert main(["scene", "convert", str(tmp_path / "std.ply"), str(tmp_path / "c.splat"), "--sh-degree", "3"]) == 2
    assert "stores SH degree 0" in capsys.readouterr().err
    (tmp_path / "junk.ply").write_bytes(b"junk")
    assert main(["scene", "info", str(tmp_path / "junk.ply")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a PLY file" in err
