"""Track data: exact simulation (torch only), the one track/batch type with its padding,
bucketing and collation, and real trajectories from any file (numpy, pymap3d, pyarrow) —
and, in :mod:`torchsde_lti.data.modules`, the only module here that imports Lightning, the
DataModules.

    tracks = tl.data.load_tracks("US_coastal_2020_06_30.traj")   # also CSV (named columns), Parquet
    rules = tl.data.CleaningRules(max_gap=600.0, v_max=35.0)     # the rules, shared by every loader
    tracks = tl.data.load_tracks("US_coastal_2020_06_30.traj", rules=rules)
    print(tracks.summary)                                        # what every cleaning rule removed
    train, val, test = tl.data.split_objects(tracks, (0.6, 0.2, 0.2), seed=0)
    windows = tl.data.track_windows(train, max_len=128)          # list of Track, metres and seconds

Out of core (:mod:`torchsde_lti.data.prepare`, :mod:`torchsde_lti.data.stream`): many files
cleaned by the same rules into a Parquet dataset, then streamed in batches
(``python -m torchsde_lti.prepare``, ``python -m torchsde_lti.train data=stream``).
"""

from torchsde_lti.data.loaded_tracks import LoadSummary, Tracks
from torchsde_lti.data.prepare import PreparedSummary, find_sources, prepare_dataset
from torchsde_lti.data.rules import AIS_NOT_AVAILABLE, REPORT_RULES, CleaningRules, ValueRule, parse_instant
from torchsde_lti.data.simulate import (
    BurstDt,
    ExponentialDt,
    RegularDt,
    diagonal_covariance,
    isotropic_covariance,
    selection_matrix,
    simulate,
    simulate_tracks,
)
from torchsde_lti.data.sources import AIS_COLUMNS, RESERVED_FOR_EVALUATION, Reports, locate_file, read_reports
from torchsde_lti.data.splits import split_objects, split_time, track_windows, window_bounds
from torchsde_lti.data.stream import WindowStream, object_split
from torchsde_lti.data.tracks import (
    BucketBatchSampler,
    EpochShuffleSampler,
    Track,
    TrackBatch,
    TrackDataset,
    collate_tracks,
    pad_tracks,
    padding_waste,
    unpad_tracks,
)
from torchsde_lti.data.trajectories import load_tracks, prepare_tracks

__all__ = [
    "AIS_COLUMNS",
    "AIS_NOT_AVAILABLE",
    "REPORT_RULES",
    "RESERVED_FOR_EVALUATION",
    "BucketBatchSampler",
    "BurstDt",
    "CleaningRules",
    "EpochShuffleSampler",
    "ExponentialDt",
    "LoadSummary",
    "PreparedSummary",
    "RegularDt",
    "Reports",
    "Track",
    "TrackBatch",
    "TrackDataset",
    "Tracks",
    "WindowStream",
    "collate_tracks",
    "diagonal_covariance",
    "find_sources",
    "isotropic_covariance",
    "load_tracks",
    "object_split",
    "locate_file",
    "pad_tracks",
    "padding_waste",
    "prepare_dataset",
    "prepare_tracks",
    "read_reports",
    "selection_matrix",
    "simulate",
    "simulate_tracks",
    "split_objects",
    "split_time",
    "track_windows",
    "unpad_tracks",
    "ValueRule",
    "parse_instant",
    "window_bounds",
]
