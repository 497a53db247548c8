"""The ``topic`` backend: object masks from label images recorded in the log."""

import numpy as np
import pytest

from mvtop_cli.errors import ConfigError
from mvtop_cli.masking.base import MaskContext, get_backend


def test_every_non_zero_label_is_the_object_without_a_label():
    labels = np.array([[0, 1, 255], [3, 0, 65535]], dtype=np.uint16)
    backend = get_backend("topic")
    assert backend.object_mask(labels).tolist() == [[False, True, True], [True, False, True]]


def test_a_label_id_picks_that_object_only():
    labels = np.array([[0, 1, 3], [3, 2, 0]], dtype=np.uint16)
    assert get_backend("topic", label=3).object_mask(labels).tolist() == [[False, False, True], [True, False, False]]


def test_proposals_are_the_recorded_mask_or_none():
    backend = get_backend("topic", label=2)
    labels = np.zeros((4, 5), np.uint16)
    labels[1:3, 2:4] = 2
    image = np.zeros((4, 5, 3), np.uint8)
    (mask,) = backend.proposals(image, MaskContext(extras={"recorded_mask": labels}))
    assert mask.sum() == 4 and mask[1:3, 2:4].all()
    assert backend.proposals(image, MaskContext()) == []


@pytest.mark.parametrize("label", [0, 70000, 1.5, True])
def test_bad_label_raises_config_error(label):
    with pytest.raises(ConfigError, match="option 'label': expected an integer 1-65535"):
        get_backend("topic", label=label)
