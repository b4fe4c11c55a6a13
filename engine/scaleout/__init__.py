"""Scale-out: floor grids and fingerprint databases traced on a Dask cluster.

``tiles`` (the raster split into tiles; how a worker process traces one),
``checkpoint`` (one NPZ per finished tile, so an interrupted build resumes),
``cluster`` (the client: local cluster or scheduler, submit, assemble). See
``docs/scaleout.md``.
"""

from .checkpoint import TileCheckpoints, checkpoint_dir, checkpoint_key
from .cluster import check_cluster_args, cluster_client, trace_grid_tiled
from .tiles import GridPlan, TileJob, plan_grid, trace_tile

__all__ = ["trace_grid_tiled", "cluster_client", "check_cluster_args",
           "TileCheckpoints", "checkpoint_dir", "checkpoint_key",
           "GridPlan", "TileJob", "plan_grid", "trace_tile"]
