"""Edge tables of risp_data.flat_projective (pure numpy): which mesh edges and crossing segments are boundaries."""

import numpy as np
import pytest

from risp_data.flat_projective import coplanar_cover, edge_table, intersection_segments, overlapping_boxes

# unit cube, outward-wound triangles (two per face)
CUBE_V = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
CUBE_F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                   [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


def test_cube_seen_from_a_corner_direction_has_six_silhouette_and_three_crease_edges():
    view = np.array([3.0, 2.5, 2.0])  # sees the +x, +y and +z faces
    din, dout, crease, w = edge_table(CUBE_V, CUBE_F, view)
    assert crease.sum() == 3 and (~crease).sum() == 6
    assert np.all(w > 0)
    n = np.cross(CUBE_V[CUBE_F[:, 1]] - CUBE_V[CUBE_F[:, 0]], CUBE_V[CUBE_F[:, 2]] - CUBE_V[CUBE_F[:, 0]])
    front = np.einsum("ij,ij->i", n, CUBE_V[CUBE_F[:, 0]] - view) < 0
    assert np.all(front[din // 3])  # f_in is always taken on a face that faces the camera
    assert np.all(front[dout[crease] // 3]) and np.all(dout[~crease] == din[~crease])
    # the same edges cast shadows from a point light there: silhouettes only
    din_l, _, crease_l, _ = edge_table(CUBE_V, CUBE_F, view, creases=False)
    assert len(din_l) == 6 and not crease_l.any()


def test_crossing_triangles_give_their_common_segment():
    a = np.array([[-1.0, -1, 0], [1, -1, 0], [0, 1, 0]])  # in z = 0
    b = np.array([[0.0, -2, -1], [0, 2, -1], [0, 0, 1]])  # in x = 0, crossing z = 0 along y ∈ [-1, 1]
    x0, x1, sa, fa, sb, fb, ba0, ba1, bb0, bb1 = intersection_segments([a, b], [np.array([[0, 1, 2]])] * 2)
    assert len(x0) == 1 and sa[0] == 0 and sb[0] == 1
    ends = sorted([tuple(np.round(x0[0], 6)), tuple(np.round(x1[0], 6))])
    assert np.allclose(ends, [(0, -1, 0), (0, 1, 0)], atol=1e-9)  # both reach y = ±1 at x = z = 0 (a: apex on the plane)
    for X, b0 in ((a, ba0[0]), (b, bb0[0])):  # barycentrics reproduce the end points
        p = X[0] + b0[0] * (X[1] - X[0]) + b0[1] * (X[2] - X[0])
        assert np.allclose(p, x0[0], atol=1e-9)
    # triangles of one mesh that share a vertex are not crossings
    assert len(intersection_segments([np.r_[a, b[:2]]], [np.array([[0, 1, 2], [2, 3, 4]])])[0]) == 0


def test_a_triangle_that_only_touches_a_plane_makes_no_crossing():
    """A blade's side face ends in the plane of the other blade's top (flush parts): it touches that plane along
    an edge, to within float32 rounding, without crossing it, so no crossing segment (its edge is a mesh edge).
    Moved 1 mm up it crosses the plane, and the segment is there."""
    top = np.array([[-1.0, -1, 0.1], [1, -1, 0.1], [0, 1, 0.1]])
    side = np.array([[0.0, -0.5, 0.1 + 3e-9], [0, 0.5, 0.1 - 3e-9], [0, 0, -0.2]])  # its top edge in z = 0.1
    face = np.array([[0, 1, 2]])
    assert len(intersection_segments([top, side], [face, face])[0]) == 0
    assert len(intersection_segments([top, side + [0, 0, 1e-3]], [face, face])[0]) == 1


def _box(extents, centre):
    import trimesh

    b = trimesh.creation.box(extents=extents)
    b.apply_translation(centre)
    return np.asarray(b.vertices), np.asarray(b.faces)


def _cover_of_crossed_bars(height_b):
    """Bar A along x (0.4 × 0.05 × 0.03), bar B along y, crossing at the origin, B's height ``height_b``; both
    bars in one mesh.  Returns A's top edges along x (seen from above: creases), their end points, and the
    covered intervals of every edge."""
    (Va, Fa), (Vb, Fb) = _box([0.4, 0.05, 0.03], [0, 0, 0]), _box([0.05, 0.4, height_b], [0, 0, 0])
    V, F = np.r_[Va, Vb], np.r_[Fa, Fb + len(Va)]
    din, dout, crease, _ = edge_table(V, F, np.array([0.3, -0.2, 3.0]))
    lo, hi = coplanar_cover([(V, F)], np.zeros(len(din), np.int64), din, [din // 3, dout // 3])
    a, b = V[F[din // 3, din % 3]], V[F[din // 3, (din % 3 + 1) % 3]]
    on_a_top = (din // 3 < len(Fa)) & np.isclose(a[:, 2], 0.015) & np.isclose(b[:, 2], 0.015) & \
        np.isclose(a[:, 1], b[:, 1])
    return on_a_top, a, b, lo, hi


def test_edges_inside_a_coplanar_face_of_another_part_are_covered():
    """Two crossed bars of one height: each top edge of bar A runs through bar B's top for |x| < 0.025, where the
    image shows the same plane on both sides.  That stretch (and no other) is covered; with B 6 mm taller the
    planes differ and nothing is."""
    on_a_top, a, b, lo, hi = _cover_of_crossed_bars(0.03)
    assert on_a_top.sum() == 2  # A's two long top edges (each a crease or a silhouette from this viewpoint)
    for k in np.nonzero(on_a_top)[0]:
        slots = lo[k] < 2
        covered = [(a[k] + u * (b[k] - a[k]))[0] for u in np.r_[lo[k][slots], hi[k][slots]]]
        assert np.isclose(min(covered), -0.025, atol=1e-5) and np.isclose(max(covered), 0.025, atol=1e-5)
        # (less a margin of 1e-6 of the coordinates at each triangle boundary, B's diagonal included)
        assert np.sum(hi[k][slots] - lo[k][slots]) == pytest.approx(0.05 / 0.4, abs=1e-4)
    covered_edges = (lo < 2).any(1)
    # the only covered edges are top and bottom edges of the two bars, inside the other bar's face
    assert covered_edges.sum() >= 2 and np.all(np.isclose(np.abs(a[covered_edges, 2]), 0.015))
    _, _, _, lo_taller, _ = _cover_of_crossed_bars(0.036)
    assert not (lo_taller < 2).any()


def test_a_part_does_not_cover_its_own_edges():
    """One box: every face is coplanar with its neighbour triangle, none covers an edge (same part)."""
    din, dout, _, _ = edge_table(CUBE_V, CUBE_F, np.array([3.0, 2.5, 2.0]))
    lo, _ = coplanar_cover([(CUBE_V, CUBE_F)], np.zeros(len(din), np.int64), din, [din // 3, dout // 3])
    assert not (lo < 2).any()


@pytest.mark.parametrize("n", [0, 1, 2, 7, 300])
def test_sweep_and_prune_finds_every_overlapping_box_pair_in_triu_order(n):
    """The broad phase of intersection_segments against all n(n-1)/2 pairs: the same pairs in the same order
    (the order fixes which segment a random number samples), touching and identical boxes included."""
    rng = np.random.default_rng(n)
    centre, half = rng.normal(size=(n, 3)), rng.uniform(0, 0.4, (n, 3))
    lo, hi = centre - half, centre + half
    if n >= 7:
        lo[1], hi[1] = lo[0], hi[0]  # identical boxes
        lo[2, 0] = hi[3, 0]  # touching along x
        hi[4] = lo[4]  # a degenerate box
    i, j = np.triu_indices(n, 1)
    ok = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
    got_i, got_j = overlapping_boxes(lo, hi)
    assert np.array_equal(got_i, i[ok]) and np.array_equal(got_j, j[ok])
    if n == 300:
        assert 0 < ok.sum() < len(i)  # some pairs overlap, some do not: the comparison means something


def test_boundary_term_is_selectable_and_leaves_the_image_alone():
    """`boundary="mitsuba"` swaps only the gradient integrator: same primal image, a different (finite) gradient;
    an unknown name is one clear error."""
    import torch

    from risp_data.diff_render import StateRenderer
    from risp_data.envs import get_environment
    from risp_data.errors import RispError

    state = torch.tensor(get_environment("hand").sample_states(np.random.default_rng(0), 1), dtype=torch.float32)
    images, grads = [], []
    for boundary in ("flat", "mitsuba"):
        r = StateRenderer("hand", resolution=16, spp=2, boundary=boundary)
        s = state.clone().requires_grad_(True)
        image = r(s, seed=3)
        image.sum().backward()
        images.append(image.detach())
        grads.append(s.grad.clone())
    assert torch.equal(images[0], images[1])
    assert all(torch.isfinite(g).all() and g.abs().sum() > 0 for g in grads)
    assert not torch.equal(grads[0], grads[1])
    with pytest.raises(RispError, match="boundary"):
        StateRenderer("hand", resolution=16, spp=2, boundary="smooth")
