"""Runs generation requests on a Ray cluster (``demo-factory generate --executor ray``).

Ray schedules the same per-episode work as the local process pool: each task is one
``run_episode`` call writing its own recording, so the files are identical whichever executor,
worker count or machine produced them. Ray is an optional extra: ``pip install 'demo_factory[ray]'``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator


def run_on_ray(episode: Callable, todo: list, address: str | None = None, num_cpus: int | None = None) -> Iterator:
    """Yield ``episode(request, out_dir)`` for each of ``todo`` = ``[(request, out_dir), ...]`` in order,
    computed by Ray workers.

    ``address`` joins an existing cluster (``ray start --head`` prints it); without it Ray starts
    a local one on this machine.
    """
    try:
        import ray
    except ImportError:
        raise RuntimeError("the ray executor needs Ray: pip install 'demo_factory[ray]'") from None
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(address=address, num_cpus=None if address else num_cpus, include_dashboard=False,
                 log_to_driver=False, configure_logging=False)
    try:
        remote_episode = ray.remote(episode)
        pending = [remote_episode.remote(request, out_dir) for request, out_dir in todo]
        for reference in pending:
            yield ray.get(reference)
    finally:
        if started_here:
            ray.shutdown()
