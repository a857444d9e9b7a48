"""The HDF5 dataset layer (SPEC section 1): write atomically, validate on load, read lazily.

* :mod:`.schema`: the file layout, its errors (:class:`SchemaError`, :class:`DatasetMissing`,
  :class:`DataError`) and :func:`validate`, the check of an open file against it;
* :mod:`.writer`: :func:`write_dataset` (a temporary file renamed into place when complete, under a lock)
  and :func:`generate_dataset` (a benchmark's generator run into the data home);
* :mod:`.reader`: :class:`Dataset`, a validated file read lazily, :func:`load_dataset`, and
  :func:`load_benchmark`, the benchmark a file describes (a custom one: your own flow, any grid);
* :mod:`.the_well`, :mod:`.pdebench`: other collections' layouts imported into the schema
  (:func:`import_the_well`, :func:`import_pdebench`, through :mod:`.importing`) and exported to them
  (:func:`export_the_well`, :func:`export_pdebench`; a flow given as arrays: :func:`write_the_well`); a file
  breaking its layout raises :class:`LayoutError`;
* :mod:`.kuramoto_sivashinsky`: a flow none of the four benchmarks is, solved and written in The Well's layout.

Files are written to a temporary name next to the target, under a lock (kept in ``$DKS_GYM_HOME/.locks``,
see :mod:`dks_gym.locks`), and renamed into place only when complete, so a failed generation, Ctrl-C,
SIGTERM or SIGHUP never leaves a file that looks valid, nor a temporary one. Reading refuses a damaged
file or NaN/inf in a trajectory with :class:`DataError`, naming the file and what to do.
"""

from .importing import LayoutError
from .pdebench import export_pdebench, import_pdebench
from .reader import Dataset, load_benchmark, load_dataset, missing_message
from .schema import (
    AXES,
    REQUIRED_ATTRS,
    SCHEMA_VERSION,
    SPLITS,
    DataError,
    DatasetMissing,
    SchemaError,
    validate,
)
from .the_well import WellFlow, export_the_well, import_the_well, write_the_well
from .writer import generate_dataset, write_dataset

__all__ = [
    "AXES",
    "REQUIRED_ATTRS",
    "SCHEMA_VERSION",
    "SPLITS",
    "DataError",
    "Dataset",
    "DatasetMissing",
    "LayoutError",
    "SchemaError",
    "WellFlow",
    "export_pdebench",
    "export_the_well",
    "generate_dataset",
    "import_pdebench",
    "import_the_well",
    "load_benchmark",
    "load_dataset",
    "missing_message",
    "validate",
    "write_dataset",
    "write_the_well",
]
