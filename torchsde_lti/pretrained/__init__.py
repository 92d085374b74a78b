r"""Trained filters shipped with the package, loaded by name, each with its card.

    import torchsde_lti as tl
    tl.pretrained.names()                        # ['ais-ny-cv', 'ais-ny-imm', ...]
    kf, card = tl.pretrained.load("ais-us-imm")  # a ready IMMFilter (float64, eval) and its ModelCard
    card.data, card.command, card.validation["metrics"], card.library_version
    tl.pretrained.check("ais-us-imm")            # the card's validation metrics, recomputed

Every shipped filter is loaded and its card's validation metrics reproduced by the test suite
at every commit (tests/pretrained), so a change of the library that breaks one fails there.
Cards of older formats (and their weights) keep loading (:func:`load_card`); a card's
``format`` says which it is.
"""

from torchsde_lti.pretrained.registry import (
    FILES,
    FORMAT,
    REMOVED_OPTIONS,
    VALIDATION_METRICS,
    ModelCard,
    Pretrained,
    card,
    check,
    load,
    load_card,
    names,
    read_card,
    save_validation_tracks,
    validation_metrics,
    validation_tracks,
)

__all__ = [
    "FILES",
    "FORMAT",
    "REMOVED_OPTIONS",
    "VALIDATION_METRICS",
    "ModelCard",
    "Pretrained",
    "card",
    "check",
    "load",
    "load_card",
    "names",
    "read_card",
    "save_validation_tracks",
    "validation_metrics",
    "validation_tracks",
]
