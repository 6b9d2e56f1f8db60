from dataclasses import dataclass, fields

import pytest

from cystomap.errors import InputError
from cystomap.settings import from_mapping, setting, validate


@dataclass(frozen=True)
class Demo:
    count: int = 3
    ratio: float = 0.5
    flag: bool = False
    sizes: tuple[float, ...] = (1.0, 2.0)
    name: str | None = None


def test_defaults_and_coercion():
    cfg = from_mapping(Demo, {"count": 4.0, "ratio": 1, "sizes": [3, 4, 5]}, "demo")
    assert cfg == Demo(count=4, ratio=1.0, sizes=(3.0, 4.0, 5.0))
    assert from_mapping(Demo, None, "demo") == Demo()


@pytest.mark.parametrize(
    ("mapping", "message"),
    [
        ({"cuont": 1}, "config demo: unknown key(s) cuont"),
        ({"count": 1.5}, "config demo.count: expected an integer"),
        ({"ratio": "high"}, "config demo.ratio: expected a number"),
        ({"flag": "yes"}, "config demo.flag: expected true or false"),
        ({"sizes": 3}, "config demo.sizes: expected a list"),
    ],
)
def test_bad_values_name_the_key(mapping, message):
    with pytest.raises(InputError) as err:
        from_mapping(Demo, mapping, "demo")
    assert message in str(err.value)


@dataclass(frozen=True)
class Ranged:
    width: int = setting(16, ">= 16")
    share: float = setting(0.5, "[0, 1)")
    level: int = setting(250, "(0, 255]")
    mode: str = setting("a", choices=("a", "b"))
    low: float = 1.0
    high: float = 2.0

    def __post_init__(self) -> None:
        validate(self, "ranged", {"low < high": self.low < self.high})


def test_ranges_are_checked_where_declared():
    Ranged(width=16, share=0.0, level=255, mode="b")
    with pytest.raises(ValueError, match=r"need width >= 16 \(got 15\)"):
        Ranged(width=15)
    with pytest.raises(ValueError, match=r"need 0 <= share < 1 \(got 1.0\), 0 < level <= 255 \(got 0\)"):
        Ranged(share=1.0, level=0)
    with pytest.raises(ValueError, match=r"mode in \(a, b\), not 'c'"):
        Ranged(mode="c")
    with pytest.raises(ValueError, match="need low < high"):
        Ranged(low=3.0)
    with pytest.raises(InputError, match="config ranged: invalid ranged settings: need width >= 16"):
        from_mapping(Ranged, {"width": 8}, "ranged")
    assert fields(Ranged)[0].default == 16  # the schema test reads the defaults from here


def test_a_malformed_range_fails_at_declaration():
    with pytest.raises(ValueError, match="bad range"):
        setting(1, "between 0 and 2")
