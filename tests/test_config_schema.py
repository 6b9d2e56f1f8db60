"""The config schema documents every key, and its defaults are the library's defaults."""

import dataclasses

import jsonschema
import pytest
import yaml

from cystomap import configdoc, configschema
from cystomap.sessions import PHANTOM_STUDY_KEYS
from cystomap.settings import setting, validate

SECTIONS = configschema.sections()
SCHEMA_WORDS = {
    "type", "default", "description", "items", "minItems", "maxItems", "minimum", "maximum",
    "exclusiveMinimum", "exclusiveMaximum", "enum", "pattern", "properties", "required",
    "additionalProperties", "anyOf", "$ref", "minLength",
}


@pytest.fixture(scope="module")
def schema(repo):
    return yaml.safe_load((repo / "workflow/schemas/config.schema.yaml").read_text())


def walk(node, path=""):
    for name, prop in node.get("properties", {}).items():
        yield f"{path}{name}", prop
        yield from walk(prop, f"{path}{name}.")


def test_every_key_is_described_with_known_keywords(schema):
    defs = {f"$defs.{k}.": v for k, v in schema["$defs"].items()}
    for prefix, node in [("", schema), *defs.items()]:
        for key, prop in walk(node, prefix):
            assert prop.get("description"), f"{key} has no description"
            assert set(prop) <= SCHEMA_WORDS, f"{key}: unexpected schema words {set(prop) - SCHEMA_WORDS}"


@pytest.mark.parametrize("section", sorted(SECTIONS))
def test_schema_defaults_are_the_dataclass_defaults(schema, section):
    props = schema["$defs"][section]["properties"]
    fields = {f.name: f.default for f in dataclasses.fields(SECTIONS[section])}
    extra = set(PHANTOM_STUDY_KEYS) if section == "phantom" else set()
    assert set(props) - extra == set(fields), f"schema {section} keys differ from the dataclass"
    for name, default in fields.items():
        value = props[name]["default"]
        assert (tuple(value) if isinstance(value, list) else value) == default, f"{section}.{name}"
    assert schema["$defs"][section].get("additionalProperties") is False


def test_every_default_is_valid_under_the_schema(schema):
    """What Snakemake fills in from the defaults must pass the schema it came from."""
    defaults = {name: {k: p["default"] for k, p in schema["$defs"][name]["properties"].items()}
                for name in SECTIONS}
    jsonschema.Draft202012Validator(schema).validate(defaults)


def test_repository_config_is_valid_and_complete(repo, schema):
    config = yaml.safe_load((repo / "config.yaml").read_text())
    jsonschema.Draft202012Validator(schema).validate(config)


def test_readme_config_table_is_up_to_date(repo):
    readme = (repo / "README.md").read_text()
    assert configdoc.block() in readme, "run: python -m cystomap.configdoc --write README.md"


def test_schema_file_is_generated_from_the_dataclasses():
    """The stage sections have one source: the dataclasses (type, default, range, comment)."""
    assert configschema.SCHEMA.read_text() == configschema.text(), (
        "run: python -m cystomap.configschema --write && python -m cystomap.configdoc --write README.md")


def test_generated_schema_carries_ranges_choices_and_comments():
    @dataclasses.dataclass(frozen=True)
    class Demo:
        # --- a group header, not a description ---
        # Share of the frames.
        share: float = setting(0.5, "[0, 1)")
        level: int = setting(3, "> 0")
        # The mode.
        mode: str = setting("a", choices=("a", "b"))
        # Lengths (mm).
        sizes: tuple[float, ...] = setting((1.0, 2.0), "> 0")
        # Kinds.
        kinds: tuple[str, ...] = setting((), choices=("x", "y"))
        # Optional centre.
        center: tuple[float, float] | None = None

        def __post_init__(self) -> None:
            validate(self, "demo")

    props = configschema.section_schema(Demo, "demo")["properties"]
    assert props["share"] == {"type": "number", "minimum": 0, "exclusiveMaximum": 1, "default": 0.5,
                              "description": "Share of the frames."}
    assert props["level"]["exclusiveMinimum"] == 0 and props["level"]["description"] == "See share."
    assert props["mode"]["enum"] == ["a", "b"]
    assert props["sizes"]["items"] == {"type": "number", "exclusiveMinimum": 0}
    assert props["kinds"]["items"] == {"type": "string", "enum": ["x", "y"]} and "enum" not in props["kinds"]
    assert props["center"]["type"] == ["array", "null"] and props["center"]["maxItems"] == 2
    with pytest.raises(ValueError, match=r"sizes > 0 \(got \(1.0, -2.0\)\)"):
        Demo(sizes=(1.0, -2.0))
    Demo(center=None)


def test_a_field_without_comment_and_no_previous_one_is_an_error():
    @dataclasses.dataclass
    class Bare:
        width: int = 3

    with pytest.raises(ValueError, match="Bare: no comment above field"):
        configschema.field_docs(Bare)


BRITISH_AMERICAN = [("centre", "center"), ("colour", "color"), ("grey", "gray"),
                    ("neighbour", "neighbor"), ("metre", "meter"), ("analyse", "analyze"),
                    ("normalise", "normalize"), ("behaviour", "behavior")]


def test_config_keys_spell_each_word_one_way(schema):
    keys = [key for node in [schema, *schema["$defs"].values()] for key, _ in walk(node)]
    words = [w for key in keys for w in key.split(".")[-1].split("_")]
    for uk, us in BRITISH_AMERICAN:
        both = [w for w in words if w.startswith(uk)], [w for w in words if w.startswith(us)]
        assert not (both[0] and both[1]), f"config keys spell {uk}/{us} both ways: {both}"
