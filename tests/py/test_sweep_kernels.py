"""The sweep/select kernels against independent implementations, through the hidden
`aret-pipe kernel` developer command (docs/kernels.md) on MetaImage files written here.

- connected components: scipy.ndimage.label (same numbering and sizes) and cc3d (same partition;
  cc3d numbers differently), connectivity 6, 18 and 26, random masks of several densities;
- morphology: scipy.ndimage.binary_dilation / binary_erosion with the ball, and the SPEC's closing
  `binary_closing(np.pad(mask, r), ball)[r:-r, r:-r, r:-r]`;
- percentiles: numpy's default `np.percentile`;
- marching cubes: trimesh reads our OBJ as watertight, winding-consistent, outward (positive
  volume) and with our enclosed volume; pyvista (VTK) and pymeshlab agree on the volume; a
  voxelised sphere's mesh volume is within 3 % of its voxel volume.

Arrays here are numpy's (z, y, x); our volumes are x-fastest, which is the same bytes.
"""
import subprocess

import cc3d
import numpy as np
import pymeshlab
import pytest
import pyvista as pv
import scipy.ndimage as ndi
import trimesh

from kernel_io import BIN, kernel, read_mhd, write_mhd

STRUCTURE = {6: 1, 18: 2, 26: 3}  # connectivity → scipy's generate_binary_structure rank


def ball(r):
    z, y, x = np.mgrid[-r:r + 1, -r:r + 1, -r:r + 1]
    return x * x + y * y + z * z <= r * r


def random_mask(seed, shape, density):
    return np.random.default_rng(seed).random(shape) < density


def union_of_balls(seed, shape, count, radii):
    rng = np.random.default_rng(seed)
    z, y, x = np.indices(shape)
    mask = np.zeros(shape, bool)
    for _ in range(count):
        c = [rng.uniform(0, n - 1) for n in shape]
        r = rng.uniform(*radii)
        mask |= (z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2 <= r * r
    return mask


# --- connected components -------------------------------------------------------------------

@pytest.mark.parametrize("connectivity", [6, 18, 26])
@pytest.mark.parametrize("density", [0.05, 0.2, 0.3, 0.45, 0.7])
def test_components_equal_scipy_label_and_cc3d(tmp_path, connectivity, density):
    mask = random_mask(int(density * 100) + connectivity, (23, 29, 31), density)
    write_mhd(tmp_path / "mask.mhd", mask.astype(np.uint8))
    out = kernel("components", tmp_path / "mask.mhd", tmp_path / "labels.mhd", "--connectivity", connectivity)
    ours = read_mhd(tmp_path / "labels.mhd")
    expected, count = ndi.label(mask, ndi.generate_binary_structure(3, STRUCTURE[connectivity]))
    np.testing.assert_array_equal(ours, expected)
    assert out["count"] == count
    assert out["sizes"] == np.bincount(expected.ravel(), minlength=count + 1)[1:].tolist()
    # cc3d numbers its own way: the same partition means a one-to-one pairing of labels.
    theirs = cc3d.connected_components(mask, connectivity=connectivity)
    pairs = np.unique(np.stack([ours[mask], theirs[mask]]), axis=1)
    assert pairs.shape[1] == count == theirs.max()
    assert len(np.unique(pairs[0])) == len(np.unique(pairs[1])) == count


@pytest.mark.parametrize("connectivity", [6, 26])
def test_dropping_small_components_equals_relabelling_the_kept(tmp_path, connectivity):
    mask = random_mask(5, (20, 24, 28), 0.25)
    write_mhd(tmp_path / "mask.mhd", mask.astype(np.uint8))
    out = kernel("components", tmp_path / "mask.mhd", tmp_path / "labels.mhd", "--connectivity", connectivity,
                 "--min-voxels", 10)
    structure = ndi.generate_binary_structure(3, STRUCTURE[connectivity])
    labels, count = ndi.label(mask, structure)
    sizes = np.bincount(labels.ravel())
    kept = (sizes >= 10)[labels] & mask
    expected, kept_count = ndi.label(kept, structure)
    assert 0 < kept_count < count
    np.testing.assert_array_equal(read_mhd(tmp_path / "labels.mhd"), expected)
    assert out["sizes"] == np.bincount(expected.ravel())[1:].tolist()


def test_a_bad_connectivity_is_a_clear_error(tmp_path):
    write_mhd(tmp_path / "mask.mhd", np.ones((2, 2, 2), np.uint8))
    proc = subprocess.run([BIN, "kernel", "components", str(tmp_path / "mask.mhd"), str(tmp_path / "l.mhd"),
                           "--connectivity", "8"], capture_output=True, text=True)
    assert proc.returncode != 0
    assert "connectivity must be 6, 18 or 26" in proc.stderr and "got 8" in proc.stderr


# --- morphology -----------------------------------------------------------------------------

MORPH_MASKS = {
    "noise": lambda: random_mask(1, (21, 26, 30), 0.3),
    "sparse": lambda: random_mask(2, (21, 26, 30), 0.05),
    "dense": lambda: random_mask(3, (21, 26, 30), 0.85),
    "balls": lambda: union_of_balls(4, (24, 30, 70), 8, (1.5, 5.0)),  # nx > 64: two words a row
    "border": lambda: np.pad(np.ones((6, 8, 10), bool), ((0, 5), (3, 0), (0, 0))),  # touches faces
}


@pytest.mark.parametrize("name", sorted(MORPH_MASKS))
@pytest.mark.parametrize("radius", [1, 2, 3])
def test_morphology_equals_scipy(tmp_path, name, radius):
    mask = MORPH_MASKS[name]()
    write_mhd(tmp_path / "mask.mhd", mask.astype(np.uint8))
    b = ball(radius)
    expected = {
        "dilate": ndi.binary_dilation(mask, b),
        "erode": ndi.binary_erosion(mask, b),
        "close": ndi.binary_closing(np.pad(mask, radius), b)[radius:-radius, radius:-radius, radius:-radius],
    }
    for op, want in expected.items():
        out = kernel(op, tmp_path / "mask.mhd", tmp_path / f"{op}.mhd", "--radius", radius)
        got = read_mhd(tmp_path / f"{op}.mhd")
        np.testing.assert_array_equal(got.astype(bool), want, err_msg=f"{op} r={radius} on {name}")
        assert out["voxels"] == int(want.sum())


def test_the_radius_2_ball_has_33_offsets():
    assert ball(2).sum() == 33


# --- percentiles ----------------------------------------------------------------------------

PERCENTILES = [0, 0.5, 25, 50, 85, 88, 90, 91, 92, 93, 94, 95, 96, 97, 98, 99, 99.9, 100]


@pytest.mark.parametrize("n", [1, 2, 7, 1000, 262144])
def test_percentiles_equal_numpy(tmp_path, n):
    rng = np.random.default_rng(n)
    values = rng.lognormal(-3.0, 1.5, n)
    values[: n // 10] = np.round(values[: n // 10], 2)  # ties
    write_mhd(tmp_path / "v.mhd", values.reshape(1, 1, n))
    out = kernel("percentiles", tmp_path / "v.mhd", "--p", ",".join(map(str, PERCENTILES)))
    np.testing.assert_allclose(out["values"], np.percentile(values, PERCENTILES), rtol=1e-12, atol=0)
    # float32 volumes (the density grid) are widened to float64 first.
    as_f32 = values.astype(np.float32)
    write_mhd(tmp_path / "f.mhd", as_f32.reshape(1, 1, n))
    out = kernel("percentiles", tmp_path / "f.mhd", "--p", ",".join(map(str, PERCENTILES)))
    np.testing.assert_allclose(out["values"], np.percentile(as_f32.astype(np.float64), PERCENTILES), rtol=1e-12,
                               atol=0)


# --- marching cubes -------------------------------------------------------------------------

def sphere(shape, radius_vox, offset=(0.3, -0.2, 0.1)):
    z, y, x = np.indices(shape, dtype=float)
    c = [(n - 1) / 2 + o for n, o in zip(shape, offset)]
    return (z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2 <= radius_vox ** 2


def torus(shape, major, minor):
    z, y, x = np.indices(shape, dtype=float)
    c = [(n - 1) / 2 for n in shape]
    ring = np.sqrt((x - c[2]) ** 2 + (y - c[1]) ** 2) - major
    return ring ** 2 + (z - c[0]) ** 2 <= minor ** 2


def hollow():
    outer, inner = sphere((24, 24, 24), 9.5), sphere((24, 24, 24), 5.0)
    return outer & ~inner  # a closed cavity inside: two surfaces, the inner one facing in


def diagonal_contacts():
    m = np.zeros((9, 9, 9), bool)
    m[2, 2, 2] = m[3, 3, 3] = True  # corner contact
    m[5, 5, 2] = m[5, 6, 3] = True  # edge contact
    m[6:8, 6:8, 6:8] = True
    m[5, 5, 5] = True  # corner of a block
    return m


MESH_CASES = {
    "sphere r7": (lambda: sphere((20, 20, 20), 7.0), (1.0, 1.0, 1.0)),
    "sphere r6 anisotropic": (lambda: sphere((18, 18, 18), 6.0), (3.75, 1.875, 2.1875)),
    "sphere r8 thick slices": (lambda: sphere((21, 21, 21), 8.0), (0.7, 0.7, 2.5)),
    "union of balls": (lambda: union_of_balls(7, (26, 30, 34), 10, (1.0, 5.0)), (1.0, 1.2, 1.5)),
    "torus (a tunnel)": (lambda: torus((12, 30, 30), 8.0, 3.0), (1.0, 1.0, 1.0)),
    "hollow ball (a cavity)": (hollow, (1.0, 1.0, 1.0)),
    "diagonal contacts": (diagonal_contacts, (1.0, 1.0, 1.0)),
    "noise 0.3 (every ambiguous case)": (lambda: random_mask(8, (14, 15, 16), 0.3), (1.0, 2.0, 0.5)),
    "noise 0.6": (lambda: random_mask(9, (14, 15, 16), 0.6), (1.0, 1.0, 1.0)),
    "touching the border": (lambda: np.pad(sphere((16, 16, 16), 9.0), ((0, 0), (0, 3), (2, 0))), (1.0, 1.0, 1.0)),
}
ORIGIN = (-120.0, 35.5, -310.25)
SPHERE_ERRORS = {}


@pytest.fixture(scope="module", params=sorted(MESH_CASES))
def meshed(request, tmp_path_factory):
    make, spacing = MESH_CASES[request.param]
    mask = make()
    tmp = tmp_path_factory.mktemp("mesh")
    write_mhd(tmp / "mask.mhd", mask.astype(np.uint8), spacing=spacing, origin=ORIGIN)
    summary = kernel("mesh", tmp / "mask.mhd", tmp / "mesh.obj")
    return request.param, mask, spacing, tmp / "mesh.obj", summary


def test_trimesh_reads_a_watertight_outward_mesh_with_our_volume(meshed):
    name, mask, spacing, path, summary = meshed
    assert summary["closed_and_oriented"]
    mesh = trimesh.load(path, force="mesh", process=False)
    assert len(mesh.vertices) == summary["vertices"] and len(mesh.faces) == summary["triangles"]
    assert mesh.is_watertight, name
    assert mesh.is_winding_consistent, name
    assert mesh.volume > 0, f"{name}: normals point inwards"
    assert mesh.volume == pytest.approx(summary["enclosed_volume_mm3"], rel=1e-6)
    # Viewers weld vertices by position: our vertices are distinct, so nothing changes.
    welded = trimesh.load(path, force="mesh")
    assert len(welded.vertices) == len(mesh.vertices) and welded.is_watertight and welded.is_winding_consistent
    # Patient mm: every vertex within half a voxel of the mask's voxel centres.
    idx = np.argwhere(mask)[:, ::-1]  # (x, y, z)
    lo = np.array(ORIGIN) + (idx.min(0) - 0.5) * spacing
    hi = np.array(ORIGIN) + (idx.max(0) + 0.5) * spacing
    assert (mesh.vertices >= lo - 1e-9).all() and (mesh.vertices <= hi + 1e-9).all()
    header = path.read_text().splitlines()[:3]
    assert any("mm, patient LPS" in line for line in header)


def test_pyvista_and_pymeshlab_agree_on_the_volume(meshed):
    name, _, _, path, summary = meshed
    ours = summary["enclosed_volume_mm3"]
    assert pv.read(path).volume == pytest.approx(ours, rel=1e-6), name
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(path))
    topology = ms.get_topological_measures()
    assert topology["boundary_edges"] == 0 and topology["non_two_manifold_edges"] == 0, name
    assert topology["non_two_manifold_vertices"] == 0, name
    assert ms.get_geometric_measures()["mesh_volume"] == pytest.approx(ours, rel=1e-6), name


@pytest.mark.parametrize("name", [n for n in sorted(MESH_CASES) if n.startswith("sphere")])
def test_a_voxelised_spheres_mesh_encloses_its_voxel_volume(tmp_path, name):
    make, spacing = MESH_CASES[name]
    mask = make()
    write_mhd(tmp_path / "mask.mhd", mask.astype(np.uint8), spacing=spacing, origin=ORIGIN)
    summary = kernel("mesh", tmp_path / "mask.mhd", tmp_path / "mesh.obj")
    voxel_volume = mask.sum() * np.prod(spacing)
    assert summary["voxel_volume_mm3"] == pytest.approx(voxel_volume, rel=1e-12)
    error = summary["enclosed_volume_mm3"] / voxel_volume - 1
    print(f"\n{name}: mesh {summary['enclosed_volume_mm3']:.2f} mm³, voxels {voxel_volume:.2f} mm³, "
          f"error {100 * error:+.2f} %")
    assert abs(error) < 0.03
