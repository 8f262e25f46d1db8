"""Tracer: exact hits on known geometry, occlusion, and point-cloud surfels against the mesh."""

from __future__ import annotations

import numpy as np
import pytest

from mvintrinsic import Proxy
from mvintrinsic.raytrace import Tracer

HIT_TOL = 1e-5  # m: Embree works in float32


def box_proxy(points_only=False, subdivisions=4):
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_box(2.0, 2.0, 2.0).translate((-1.0, -1.0, 0.0))
    mesh = mesh.subdivide_midpoint(subdivisions)
    mesh.remove_duplicated_vertices()
    mesh.compute_vertex_normals()
    v, n, t = np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals), np.asarray(mesh.triangles)
    return Proxy(v, n) if points_only else Proxy(v, n, t)


def test_hits_on_a_box_are_exact():
    tracer = Tracer(box_proxy())
    origins = np.array([[0.3, -0.2, 10.0], [5.0, 0.5, 1.0], [0.0, 0.0, 5.0]])
    directions = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    hits = tracer.intersect(origins, directions)
    assert hits.hit.tolist() == [True, True, False]
    np.testing.assert_allclose(hits.t[:2], [8.0, 4.0], atol=HIT_TOL)
    np.testing.assert_allclose(hits.points[:2], [[0.3, -0.2, 2.0], [1.0, 0.5, 1.0]], atol=HIT_TOL)
    np.testing.assert_allclose(hits.normals[:2], [[0, 0, 1], [1, 0, 0]], atol=1e-6)
    assert np.isinf(hits.t[2]) and np.isnan(hits.points[2]).all() and hits.vertex[2] == hits.triangle[2] == -1
    # The reported triangle contains the hit point and the reported vertex is one of its corners.
    proxy = tracer.proxy
    for i in range(2):
        corners = proxy.vertices[proxy.triangles[hits.triangle[i]]]
        assert hits.vertex[i] in proxy.triangles[hits.triangle[i]]
        a, b, c = corners
        area = np.linalg.norm(np.cross(b - a, c - a))
        sub = sum(np.linalg.norm(np.cross(q - hits.points[i], r - hits.points[i])) for q, r in ((a, b), (b, c), (c, a)))
        assert sub == pytest.approx(area, rel=1e-5)
    # The reported vertex is the nearest corner of the hit triangle.
    v = tracer.proxy.vertices[hits.vertex[:2]]
    dist = np.linalg.norm(v - hits.points[:2], axis=1)
    nearest = np.min(np.linalg.norm(tracer.proxy.vertices[None] - hits.points[:2, None], axis=2), axis=1)
    np.testing.assert_allclose(dist, nearest, atol=1e-9)


def test_t_range_and_occlusion():
    tracer = Tracer(box_proxy())
    o = np.array([[0.0, 0.0, 10.0]])
    d = np.array([[0.0, 0.0, -1.0]])
    assert not tracer.intersect(o, d, t_max=7.9).hit[0]
    assert tracer.intersect(o, d, t_min=8.5).t[0] == pytest.approx(10.0, abs=HIT_TOL)  # the floor of the box
    assert tracer.occluded(o, d).tolist() == [True]
    assert tracer.occluded(o, d, t_max=7.9).tolist() == [False]
    assert tracer.occluded(o, -d).tolist() == [False]


def test_batches_give_the_same_answer():
    rng = np.random.default_rng(0)
    tracer = Tracer(box_proxy())
    d = rng.normal(size=(1000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.array([0.0, 0.0, 5.0])
    a, b = tracer.intersect(o, d), tracer.intersect(o, d, batch=97)
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(tracer.occluded(o, d), tracer.occluded(o, d, batch=13))


def test_point_cloud_surfels_close_the_surface():
    mesh, cloud = Tracer(box_proxy()), Tracer(box_proxy(points_only=True))
    rng = np.random.default_rng(1)
    # Rays from above onto the top face, away from its edges.
    origins = np.column_stack([rng.uniform(-0.9, 0.9, 500), rng.uniform(-0.9, 0.9, 500), np.full(500, 5.0)])
    d = np.tile([0.0, 0.0, -1.0], (500, 1))
    a, b = mesh.intersect(origins, d), cloud.intersect(origins, d)
    assert a.hit.all() and b.hit.all()
    np.testing.assert_allclose(b.t, a.t, atol=1e-5)  # surfels lie in the face plane
    # The reported point is the centre of the hit surfel: within the square's half-diagonal,
    # sqrt(2) * (mean distance to the 6 nearest neighbours), of the hit point.
    from scipy.spatial import cKDTree

    points = cloud.proxy.vertices
    spacing = cKDTree(points).query(points, k=7)[0][:, 1:].mean(axis=1)
    dist = np.linalg.norm(points[b.vertex] - b.points, axis=1)
    assert np.all(dist <= np.sqrt(2) * spacing[b.vertex] + 1e-6)


def test_rejects_bad_rays():
    tracer = Tracer(box_proxy(subdivisions=0))
    with pytest.raises(ValueError, match="directions"):
        tracer.intersect(np.zeros(3), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="origins"):
        tracer.intersect(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(TypeError, match="proxy"):
        Tracer("box")  # type: ignore[arg-type]
