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
"""

from torchsde_lti.data.loaded_tracks import LoadSummary, Tracks
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
    "RegularDt",
    "Reports",
    "Track",
    "TrackBatch",
    "TrackDataset",
    "Tracks",
    "collate_tracks",
    "diagonal_covariance",
    "isotropic_covariance",
    "load_tracks",
    "locate_file",
    "pad_tracks",
    "padding_waste",
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
