"""Open3D's pose graph (``pipelines.registration``) for :func:`~linereg.registration.multiway.register_scans`:
the information matrix of an edge and the global optimisation with its line process."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from linereg.registration.multiway import Edge, MultiwayOptions


def information(source, target, distance: float, transformation: np.ndarray) -> np.ndarray:
    """``(6, 6)`` information matrix of the edge ``transformation (4, 4)`` between the Open3D clouds
    ``source`` and ``target``, from their correspondences within ``distance`` (Open3D's; entry
    ``[5, 5]`` counts them)."""
    import open3d as o3d

    registration = o3d.pipelines.registration
    return np.asarray(registration.get_information_matrix_from_point_clouds(source, target, distance, transformation))


def optimise_graph(
    initial: list[np.ndarray | None],
    edges: list[Edge],
    informations: dict[int, np.ndarray],
    distance: float,
    options: MultiwayOptions,
) -> tuple[list[np.ndarray], list[Edge]]:
    """Open3D's ``global_optimization`` of ``edges`` (their information matrices by ``id``;
    :attr:`~linereg.registration.multiway.Edge.uncertain` ones prunable) from the ``initial`` poses
    (identity where ``None``), correspondences within ``distance``: the optimised poses and the edges it kept."""
    import open3d as o3d

    registration = o3d.pipelines.registration
    graph = registration.PoseGraph()
    for pose in initial:
        graph.nodes.append(registration.PoseGraphNode(np.eye(4) if pose is None else pose))
    for edge in edges:
        graph.edges.append(
            registration.PoseGraphEdge(
                edge.source,
                edge.target,
                edge.transformation,
                informations[id(edge)],
                uncertain=edge.uncertain,
            )
        )
    settings = registration.GlobalOptimizationOption(
        max_correspondence_distance=distance,
        edge_prune_threshold=options.edge_prune_threshold,
        preference_loop_closure=options.preference_loop_closure,
        reference_node=0,
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        registration.global_optimization(
            graph,
            registration.GlobalOptimizationLevenbergMarquardt(),
            registration.GlobalOptimizationConvergenceCriteria(),
            settings,
        )
    remaining = [(left.source_node_id, left.target_node_id, np.asarray(left.transformation)) for left in graph.edges]
    kept, start = [], 0
    for edge in edges:
        for n in range(start, len(remaining)):
            source, target, transform = remaining[n]
            if (source, target) == (edge.source, edge.target) and np.allclose(transform, edge.transformation):
                kept.append(edge)
                start = n + 1
                break
    return [np.asarray(node.pose) for node in graph.nodes], kept
