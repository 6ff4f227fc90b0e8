"""The one spelling of the conv switch (``standard`` | ``projected``) and its deprecated aliases."""
import pytest

from omnidl.models import create_model
from omnidl.nn.conv_switch import CONV_CHOICES, DEPRECATED_CONV_SPELLINGS, conv_choice


@pytest.mark.parametrize("model", sorted(DEPRECATED_CONV_SPELLINGS))
def test_old_spellings_map_to_the_new_one_with_a_warning(model):
    for old, new in DEPRECATED_CONV_SPELLINGS[model].items():
        assert new in CONV_CHOICES
        with pytest.warns(DeprecationWarning, match=f"conv={new!r}"):
            assert conv_choice(old, model) == new


@pytest.mark.parametrize("conv", CONV_CHOICES)
def test_new_spellings_pass_silently(conv, recwarn):
    assert conv_choice(conv, "FreDSNet") == conv
    assert not [w for w in recwarn if issubclass(w.category, DeprecationWarning)]


def test_unknown_spelling_names_the_choices():
    with pytest.raises(ValueError, match="'standard' or 'projected'"):
        conv_choice("deform", "HoLiNet")
    with pytest.raises(ValueError, match="conv must be"):
        conv_choice("equi", "unet")          # an old spelling of another model is not an alias here


def test_a_model_built_with_an_old_spelling_still_builds_the_same_layers():
    with pytest.warns(DeprecationWarning):
        old = create_model("holinet", backbone="resnet18", width=0.125, conv="equi")
    new = create_model("holinet", backbone="resnet18", width=0.125, conv="projected")
    assert [type(m).__name__ for m in old.modules()] == [type(m).__name__ for m in new.modules()]
