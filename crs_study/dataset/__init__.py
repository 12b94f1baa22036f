"""The dataset stage: the stored BIDS dataset (datatype ``beh``), the only thing analysis reads.

* :mod:`~crs_study.dataset.schema`: the vocabulary (trial columns, the task, ``n/a``) and how
  a value is written in a cell;
* :mod:`~crs_study.dataset.session_metadata`: a session's sidecar as typed data
  (:class:`SessionMetadata`, read strictly);
* :mod:`~crs_study.dataset.bids`: every path of the layout, built and found
  (:class:`SessionPaths`, :func:`find_sessions`), for the writer and the reader alike;
* :mod:`~crs_study.dataset.folder`: the dataset's shared files and its participants
  (:class:`Dataset`);
* :mod:`~crs_study.dataset.session_store`: one session's files, written durably trial by
  trial (:class:`SessionStore`);
* :mod:`~crs_study.dataset.outputs`: the record of analysis outputs computed from the
  dataset, wherever they were written (so a withdrawal reaches each).
"""

from crs_study.dataset.bids import SessionPaths, beh_files, derivatives_dir, find_sessions
from crs_study.dataset.folder import (
    ARRIVALS_FILE,
    DATASET_LOCK,
    WITHDRAWAL_JOURNAL,
    Dataset,
    check_label,
    column_dictionary,
    dataset_dir,
    is_simulated_label,
    utc_now,
)
from crs_study.dataset.outputs import OUTPUTS_REGISTRY, OutputsRecord, read_outputs
from crs_study.dataset.schema import (
    DEFAULT_TASK,
    MISSING,
    TASK,
    TRIAL_COLUMNS,
    Task,
    format_value,
    trial_columns,
)
from crs_study.dataset.session_metadata import SessionMetadata
from crs_study.dataset.session_store import SessionStore, read_frame_log

__all__ = ["ARRIVALS_FILE", "DATASET_LOCK", "DEFAULT_TASK", "MISSING", "OUTPUTS_REGISTRY",
           "TASK", "TRIAL_COLUMNS", "WITHDRAWAL_JOURNAL", "Dataset", "OutputsRecord",
           "SessionMetadata", "SessionPaths", "SessionStore", "Task", "beh_files", "check_label",
           "column_dictionary", "dataset_dir", "derivatives_dir", "find_sessions",
           "format_value", "is_simulated_label", "read_frame_log", "read_outputs",
           "trial_columns", "utc_now"]
