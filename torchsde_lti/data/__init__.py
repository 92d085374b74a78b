"""Track data: exact simulation (torch only), the one track/batch type with its padding and
collation, the AIS loader (numpy), and — in :mod:`torchsde_lti.data.modules`, the only
module here that imports Lightning — the DataModules."""

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
from torchsde_lti.data.tracks import (
    EpochShuffleSampler,
    Track,
    TrackBatch,
    TrackDataset,
    collate_tracks,
    pad_tracks,
    unpad_tracks,
)

__all__ = [
    "BurstDt",
    "EpochShuffleSampler",
    "ExponentialDt",
    "RegularDt",
    "Track",
    "TrackBatch",
    "TrackDataset",
    "collate_tracks",
    "diagonal_covariance",
    "isotropic_covariance",
    "pad_tracks",
    "selection_matrix",
    "simulate",
    "simulate_tracks",
    "unpad_tracks",
]
