"""The device mesh, under its former name: the module is ``dpc_jax.engine.parallel`` (inference and
adaptation use it too, and they must not import the training package)."""

from dpc_jax.engine.parallel import DATA_AXIS as DATA_AXIS
from dpc_jax.engine.parallel import batch_sharding as batch_sharding
from dpc_jax.engine.parallel import check_batch_size as check_batch_size
from dpc_jax.engine.parallel import initialize_distributed as initialize_distributed
from dpc_jax.engine.parallel import make_mesh as make_mesh
from dpc_jax.engine.parallel import process_slice as process_slice
from dpc_jax.engine.parallel import replicate as replicate
from dpc_jax.engine.parallel import replicated as replicated
from dpc_jax.engine.parallel import shard_batch as shard_batch
