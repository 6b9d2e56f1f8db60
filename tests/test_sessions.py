import pytest

from cystomap.errors import InputError
from cystomap.sessions import load_sheet

CAMERAS = {"scope": {"width": 320, "height": 180, "diagonal_fov_deg": 76}}
HEADER = "subject\tsession\tvideo\tdate\tcamera\textent_mm\n"


@pytest.fixture
def schema(repo):
    return repo / "workflow/schemas/sessions.schema.yaml"


def write(tmp_path, body, header=HEADER):
    path = tmp_path / "sessions.tsv"
    path.write_text(header + body)
    return path


def test_valid_sheet_is_typed(tmp_path, schema):
    path = write(tmp_path, "p01\tpre\tv1.mp4\t2026-01-02\tscope\t160\np01\tpost\tv2.mp4\t2026-03-02\tscope\t\n")
    df = load_sheet(path, CAMERAS, schema)
    assert list(df["session"]) == ["pre", "post"]
    assert df["extent_mm"].iloc[0] == 160.0
    assert df["extent_mm"].isna().iloc[1]


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("../p\ta\tv.mp4\t2026-01-02\tscope\t\n", "line 2, column subject"),
        ("p01\ta;rm -rf\tv.mp4\t2026-01-02\tscope\t\n", "line 2, column session"),
        ("p01\ta b\tv.mp4\t2026-01-02\tscope\t\n", "line 2, column session"),
        ("p01\ta\tv.mp4\t02/01/2026\tscope\t\n", "line 2, column date"),
        ("p01\ta\tv.mp4\t2026-02-31\tscope\t\n", "not an ISO date"),
        ("p01\ta\tv.mp4\t2026-01-02\tendo\t\n", "camera 'endo' is not a key"),
        ("p01\ta\tv.mp4\t2026-01-02\tscope\tbig\n", "line 2, column extent_mm"),
        ("p01\ta\tv.mp4\t2026-01-02\tscope\t-3\n", "line 2, column extent_mm"),
    ],
)
def test_bad_rows_name_line_and_column(tmp_path, schema, body, message):
    path = write(tmp_path, body)
    with pytest.raises(InputError) as err:
        load_sheet(path, CAMERAS, schema)
    assert str(path) in str(err.value)
    assert message in str(err.value)


def test_missing_column_and_missing_file(tmp_path, schema):
    path = write(tmp_path, "p01\ta\tv.mp4\n", header="subject\tsession\tvideo\n")
    with pytest.raises(InputError, match=r"missing column.*date, camera"):
        load_sheet(path, CAMERAS, schema)
    with pytest.raises(InputError, match=r"nope\.tsv: file not found"):
        load_sheet(tmp_path / "nope.tsv", CAMERAS, schema)


def test_comma_separated_sheet_is_explained(tmp_path, schema):
    path = tmp_path / "s.tsv"
    path.write_text("subject,session,video,date,camera\np,a,v.mp4,2026-01-01,scope\n")
    with pytest.raises(InputError, match="tab-separated"):
        load_sheet(path, CAMERAS, schema)


def test_anatomy_override_columns(tmp_path, schema):
    from cystomap.anatomy import AnatomyHint
    from cystomap.sessions import anatomy_overrides

    header = HEADER.rstrip("\n") + "\tentry_roll_deg\tneck_xyz\tanterior_xyz\n"
    path = write(tmp_path, "p01\tpre\tv1.mp4\t2026-01-02\tscope\t\t90\t1.5 -2 30\t\n"
                 "p01\tpost\tv2.mp4\t2026-03-02\tscope\t\t\t\t\n", header)
    df = load_sheet(path, CAMERAS, schema)
    first, second = (anatomy_overrides(r) for r in df.to_dict("records"))
    assert first == {"entry_roll_deg": 90.0, "neck_xyz": "1.5 -2 30", "anterior_xyz": None}
    assert AnatomyHint.from_mapping(first).neck_point == (1.5, -2.0, 30.0)
    assert second == {"entry_roll_deg": None, "neck_xyz": None, "anterior_xyz": None}
    bad = write(tmp_path, "p01\tpre\tv1.mp4\t2026-01-02\tscope\t\t\t1 2\t\n", header)
    with pytest.raises(InputError, match="column neck_xyz"):
        load_sheet(bad, CAMERAS, schema)
