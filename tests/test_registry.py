"""Registry.make: a setting the factory does not take is a ValueError naming the kind, the name and the setting."""

import pytest

from trivla_drake.eval.registry import Registry


def test_bad_settings_are_value_errors_naming_kind_name_and_setting_but_factory_errors_pass_through():
    things = Registry("thing")

    @things.register("box")
    def box(size: int = 1):
        if size < 0:
            raise TypeError("a box of negative size")
        return size

    assert things.make("box", size=3) == 3
    with pytest.raises(ValueError, match=r"settings of the thing 'box': unknown setting\(s\) 'colour'; it takes size"):
        things.make("box", colour="red")
    with pytest.raises(ValueError, match="settings of the thing 'box': .*too many positional"):
        things.make("box", 1, 2)
    with pytest.raises(TypeError, match="a box of negative size"):  # the factory's own error, unchanged
        things.make("box", size=-1)
    with pytest.raises(ValueError, match="unknown thing 'bag'; registered: box"):
        things.make("bag")
