"""The config schema documents every key, and its defaults are the library's defaults."""

import dataclasses

import jsonschema
import pytest
import yaml

from cystomap import configdoc
from cystomap.atlas import AtlasConfig
from cystomap.compare import CompareConfig
from cystomap.evaluate import EvalConfig
from cystomap.frames import FramesConfig
from cystomap.mesh import MeshConfig
from cystomap.phantom import PhantomConfig
from cystomap.preprocess import PreprocessConfig
from cystomap.report import ReportConfig
from cystomap.sessions import PHANTOM_STUDY_KEYS
from cystomap.sfm import SfmConfig

SECTIONS = {
    "frames": FramesConfig,
    "preprocess": PreprocessConfig,
    "phantom": PhantomConfig,
    "evaluate": EvalConfig,
    "sfm": SfmConfig,
    "mesh": MeshConfig,
    "atlas": AtlasConfig,
    "compare": CompareConfig,
    "report": ReportConfig,
}
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


def test_repository_config_is_valid_and_complete(repo, schema):
    config = yaml.safe_load((repo / "config.yaml").read_text())
    jsonschema.Draft202012Validator(schema).validate(config)


def test_readme_config_table_is_up_to_date(repo):
    readme = (repo / "README.md").read_text()
    assert configdoc.block() in readme, "run: python -m cystomap.configdoc --write README.md"
