"""Tests of :func:`warpavatar.ops.knn_graph` against the brute-force torch reference.

Neighbour lists are compared tie-aware: sorted distances must match the reference to float32 rounding,
every listed neighbour must be another, distinct point at the listed distance, and where the k-NN set is
unique (no tie among a row's k+1 nearest) the index sets must be identical.
"""

import math

import pytest
import torch

import warpavatar._src.knn as knn_bridge
from warpavatar import ops
from warpavatar._torch_impl import knn as reference

# Distances are float32 sqrt(sum of squares) on both sides; they may differ by the rounding of that sum.
DISTANCE_TOLERANCE = dict(rtol=2e-6, atol=1e-7)


def uniform_points(seed, count=700):
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(count, 3, generator=generator)


def sphere_with_outliers(seed, count=900, outliers=6):
    """Noisy unit sphere (a surface: locally 2D) plus a few points far outside it."""
    generator = torch.Generator().manual_seed(seed)
    points = torch.randn(count, 3, generator=generator)
    points = points / points.norm(dim=1, keepdim=True) + 0.003 * torch.randn(count, 3, generator=generator)
    far = torch.randn(outliers, 3, generator=generator)
    points[:outliers] = 25.0 * far / far.norm(dim=1, keepdim=True)
    return points


def clustered_points(seed):
    """Blobs of very different densities, a flat patch, a line and one lone point far away."""
    generator = torch.Generator().manual_seed(seed)
    parts = [
        0.01 * torch.randn(300, 3, generator=generator),
        torch.tensor([3.0, 0.0, 0.0]) + 0.5 * torch.randn(200, 3, generator=generator),
        torch.cat([torch.rand(150, 2, generator=generator) * 2.0, torch.zeros(150, 1)], dim=1) - 5.0,
        torch.linspace(0.0, 10.0, 60)[:, None] * torch.tensor([[0.0, 1.0, 0.0]]),
        torch.tensor([[400.0, -300.0, 250.0]]),
    ]
    points = torch.cat(parts)
    return points[torch.randperm(points.shape[0], generator=generator)]


def assert_knn_exact(points, k, index, distance, *, max_radius=None, mostly_unique=True):
    point_count = points.shape[0]
    assert index.shape == (point_count, k) and distance.shape == (point_count, k)
    assert index.dtype == torch.int64 and distance.dtype == torch.float32
    assert index.device == points.device and distance.device == points.device
    points = points.detach().cpu().float()
    index, distance = index.cpu(), distance.cpu()
    ref_index, ref_distance = reference.knn_graph(points, k, max_radius=max_radius)

    torch.testing.assert_close(distance, ref_distance, **DISTANCE_TOLERANCE)
    assert torch.equal(index < 0, ref_index < 0)
    assert torch.isinf(distance[index < 0]).all()
    assert (distance[:, 1:] >= distance[:, :-1]).all(), "rows must be sorted nearest first"

    rows = torch.arange(point_count)[:, None].expand(point_count, k)
    listed = index >= 0
    assert (index[listed] < point_count).all()
    assert (index[listed] != rows[listed]).all(), "a point is never its own neighbour"
    recomputed = (points[rows[listed]] - points[index[listed]]).norm(dim=1)
    torch.testing.assert_close(recomputed, distance[listed], **DISTANCE_TOLERANCE)
    ordered = index.sort(dim=1).values
    assert not ((ordered[:, 1:] == ordered[:, :-1]) & (ordered[:, 1:] >= 0)).any(), "a neighbour listed twice"

    # Where the k-NN set is unique, it must be the reference's set.
    _, wider = reference.knn_graph(points, k + 1, max_radius=max_radius)
    unique = (wider[:, 1:] > wider[:, :-1]).all(dim=1) | torch.isinf(wider[:, 1:]).any(dim=1)
    if mostly_unique:
        assert unique.float().mean() > 0.5  # the comparison below covers most rows
    assert torch.equal(index[unique].sort(dim=1).values, ref_index[unique].sort(dim=1).values)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_uniform_matches_brute_force(device, seed):
    points = uniform_points(seed).to(device)
    index, distance = ops.knn_graph(points, 16)
    assert_knn_exact(points, 16, index, distance)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sphere_with_outliers_matches_brute_force(device, seed):
    points = sphere_with_outliers(seed).to(device)
    index, distance = ops.knn_graph(points, 16)
    assert_knn_exact(points, 16, index, distance)
    # The outliers' neighbours are on the sphere or other outliers, at distances around 24.
    assert (distance[:6, 0] > 1.0).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_clustered_points_match_brute_force(device, seed):
    points = clustered_points(seed).to(device)
    for k in (4, 16):
        index, distance = ops.knn_graph(points, k)
        assert_knn_exact(points, k, index, distance)


def test_far_from_origin(device):
    # Coordinates near 1000 with spacing ~0.01: the grid works on centred coordinates.
    points = (1000.0 + uniform_points(3, 500) * torch.tensor([5.0, 0.2, 0.2])).to(device)
    index, distance = ops.knn_graph(points, 16)
    assert_knn_exact(points, 16, index, distance)


@pytest.mark.parametrize(
    "setting, value",
    [
        ("_CELL_SCALE", 0.03),  # tiny cells: most queries need several coarser levels
        ("_CELL_SCALE", 30.0),  # huge cells: a few cells hold everything
        ("_MIN_CELLS", 8),  # a 2x2x2 hash grid: cells alias, candidates are filtered by their own cell
    ],
)
def test_search_stays_exact_for_any_grid(device, monkeypatch, setting, value):
    monkeypatch.setattr(knn_bridge, setting, value)
    if setting == "_MIN_CELLS":
        monkeypatch.setattr(knn_bridge, "_CELLS_PER_POINT", 0)
    points = sphere_with_outliers(4, count=400).to(device)
    index, distance = ops.knn_graph(points, 16)
    assert_knn_exact(points, 16, index, distance)


def test_fewer_points_than_k(device):
    points = uniform_points(5, 4).to(device)
    index, distance = ops.knn_graph(points, 16)
    assert_knn_exact(points, 16, index, distance)
    assert (index[:, :3] >= 0).all() and (index[:, 3:] == -1).all()
    assert torch.isinf(distance[:, 3:]).all()
    index, distance = ops.knn_graph(points[:1], 4)
    assert torch.equal(index.cpu(), torch.full((1, 4), -1)) and torch.isinf(distance).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_max_radius(device, seed):
    points = sphere_with_outliers(seed, count=500).to(device)
    index, distance = ops.knn_graph(points, 16, max_radius=0.12)
    assert_knn_exact(points, 16, index, distance, max_radius=0.12)
    assert (index == -1).any() and (index >= 0).any()  # both truncated and full rows occur
    assert (distance[index >= 0] <= 0.12).all()
    # The six outliers have nothing within the radius.
    assert (index[:6] == -1).all()
    unbounded = ops.knn_graph(points, 16)
    bounded = ops.knn_graph(points, 16, max_radius=math.inf)
    assert torch.equal(unbounded[0], bounded[0])


def test_duplicates_are_neighbours_at_zero(device):
    base = uniform_points(6, 200)
    points = torch.cat([base, base, base[:50]]).to(device)
    index, distance = ops.knn_graph(points, 16)
    assert_knn_exact(points, 16, index, distance, mostly_unique=False)
    assert (distance[:, 0] == 0.0).all()
    own_copy = torch.cat([torch.arange(200, 400), torch.arange(200), torch.arange(50)]).to(device)
    assert ((index == own_copy[:, None]).any(dim=1)).all()
    # Only exact copies are kept at radius 0.
    index, distance = ops.knn_graph(points, 16, max_radius=0.0)
    copies = (index >= 0).sum(dim=1).cpu()
    assert torch.equal(copies, torch.cat([torch.full((50,), 2), torch.full((150,), 1),
                                          torch.full((50,), 2), torch.full((150,), 1), torch.full((50,), 2)]))


def test_all_points_identical(device):
    points = torch.full((20, 3), 0.5, device=device)
    index, distance = ops.knn_graph(points, 4)
    assert (distance == 0.0).all() and (index >= 0).all()
    assert (index != torch.arange(20, device=device)[:, None]).all()


def test_empty_input(device):
    index, distance = ops.knn_graph(torch.zeros(0, 3, device=device), 8)
    assert index.shape == (0, 8) and distance.shape == (0, 8)
    assert index.dtype == torch.int64 and distance.dtype == torch.float32


def test_other_float_dtypes_are_accepted(device):
    points = uniform_points(7, 300)
    index, distance = ops.knn_graph(points.double().to(device), 4)
    assert_knn_exact(points.to(device), 4, index, distance)


def test_bad_input_raises_clear_errors(device):
    points = uniform_points(8, 10).to(device)
    with pytest.raises(ValueError, match=r"points must have shape \[\*, 3\]"):
        ops.knn_graph(points[:, :2], 4)
    with pytest.raises(TypeError, match="floating-point"):
        ops.knn_graph(points.long(), 4)
    with pytest.raises(TypeError, match="torch.Tensor"):
        ops.knn_graph(points.cpu().numpy(), 4)
    with pytest.raises(ValueError, match="k must be in"):
        ops.knn_graph(points, 0)
    with pytest.raises(ValueError, match="k must be in"):
        ops.knn_graph(points, 65)
    with pytest.raises(TypeError, match="k must be an int"):
        ops.knn_graph(points, 2.0)
    with pytest.raises(ValueError, match="max_radius"):
        ops.knn_graph(points, 4, max_radius=-1.0)
    with pytest.raises(ValueError, match="max_radius"):
        ops.knn_graph(points, 4, max_radius=float("nan"))
    bad = points.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        ops.knn_graph(bad, 4)
    bad[3, 1] = float("inf")
    with pytest.raises(ValueError, match="finite"):
        ops.knn_graph(bad, 4)


def test_no_gradient(device):
    points = uniform_points(9, 50).to(device).requires_grad_()
    index, distance = ops.knn_graph(points, 4)
    assert not distance.requires_grad and not index.requires_grad
