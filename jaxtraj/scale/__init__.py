"""Scale-out: batch axes sharded over devices, and chunked processing of data on disk.

* :mod:`.shard` - :func:`reconstruct_sharded`: the point axis over a ``jax.sharding`` mesh.
* :mod:`.chunked` - :func:`run_batch`: stream tracks from ``.npy`` files in fixed chunks,
  write results incrementally, resume after an interruption (``jaxtraj batch``).
"""

from .chunked import BatchSummary as BatchSummary
from .chunked import run_batch as run_batch
from .chunked import write_dataset as write_dataset
from .shard import point_mesh as point_mesh
from .shard import reconstruct_recordings_sharded as reconstruct_recordings_sharded
from .shard import reconstruct_sharded as reconstruct_sharded
from .shard import shard_leading as shard_leading
