"""File input and output: datasets, the setup file, the calibration artifact, JSON.

Everything a user hands to hallcal goes through this package, and every mistake in it raises
:class:`hallcal.errors.HallcalInputError` with a one-line message that names the file and the
column or key at fault. Everything hallcal writes is written atomically. Nothing here unpickles
anything. Modules: :mod:`~hallcal.io.dataset`, :mod:`~hallcal.io.setup`,
:mod:`~hallcal.io.artifact`, :mod:`~hallcal.io.files`.
"""

from hallcal.io.artifact import (
    ARTIFACT_FORMAT,
    ArtifactData,
    read_artifact,
    validate_artifact,
    write_artifact,
)
from hallcal.io.dataset import (
    DATASET_EXTENSIONS,
    KNOWN_COLUMNS,
    Dataset,
    MissingColumnError,
    read_dataset,
    write_dataset,
)
from hallcal.io.files import (
    atomic_path,
    atomic_write,
    check_outputs,
    make_folder,
    output_set,
    read_json,
    to_jsonable,
    write_error,
    write_json,
)
from hallcal.io.setup import (
    BenchSpec,
    BLASpec,
    ModelSpec,
    Setup,
    TrajectorySpec,
    default_setup,
    read_setup,
    setup_from_dict,
    setup_to_toml,
    write_setup,
)

__all__ = [
    "ARTIFACT_FORMAT",
    "ArtifactData",
    "DATASET_EXTENSIONS",
    "KNOWN_COLUMNS",
    "BLASpec",
    "BenchSpec",
    "Dataset",
    "MissingColumnError",
    "ModelSpec",
    "Setup",
    "TrajectorySpec",
    "atomic_path",
    "atomic_write",
    "check_outputs",
    "default_setup",
    "make_folder",
    "output_set",
    "read_artifact",
    "read_dataset",
    "read_json",
    "read_setup",
    "setup_from_dict",
    "setup_to_toml",
    "to_jsonable",
    "validate_artifact",
    "write_artifact",
    "write_dataset",
    "write_error",
    "write_json",
    "write_setup",
]
