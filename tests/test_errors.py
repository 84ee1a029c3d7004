"""errors.translated: a library's error re-raised as ours with its cause kept; ours pass through."""

import pytest

from edmcgs.errors import CheckpointError, InvalidInputError, ReplayFormatError, translated


def _corrupt(exc: BaseException) -> ReplayFormatError:
    return ReplayFormatError(f"cannot read: {exc}")


def test_a_caught_error_becomes_ours_with_its_cause():
    with pytest.raises(ReplayFormatError, match="cannot read: 'events/t'") as info:
        with translated((OSError, KeyError), _corrupt):
            raise KeyError("events/t")
    assert isinstance(info.value.__cause__, KeyError)


def test_kept_errors_and_uncaught_ones_pass_unchanged():
    # InvalidInputError is a ValueError: kept, it is not re-worded as a corrupt file.
    with pytest.raises(InvalidInputError, match="resolution") as info:
        with translated((ValueError,), _corrupt, keep=(InvalidInputError,)):
            raise InvalidInputError("resolution 0x0")
    assert info.value.__cause__ is None
    with pytest.raises(CheckpointError):
        with translated((OSError,), _corrupt):
            raise CheckpointError("not ours to translate")
    with translated((OSError,), _corrupt):
        value = 3
    assert value == 3
