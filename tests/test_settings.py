from dataclasses import dataclass

import pytest

from cystomap.errors import InputError
from cystomap.settings import from_mapping


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
