"""Regional cost files (docs/definitions.md §21) against stacks built here by hand, and every
refusal in one line naming the file and the region."""

import pytest
import torch
import yaml

from costseg.classes import CLASS_NAMES
from costseg.costs import load_cost, save_cost

N = len(CLASS_NAMES)
PERSON = CLASS_NAMES.index("person")


def robotistic() -> torch.Tensor:
    return 1 - torch.eye(N, dtype=torch.float64)


def write(tmp_path, spec: dict, name: str = "regional.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def test_the_packaged_example_raises_person_only_in_the_street():
    stack = load_cost("configs/costs/street_person.yaml")
    expected = robotistic().expand(5, N, N).clone()
    expected[1, :, PERSON] = 10.0
    expected[1, PERSON, PERSON] = 0.0
    assert torch.equal(stack, expected)


def test_every_kind_of_entry_and_the_rois_without_one(tmp_path):
    (tmp_path / "plain.yaml").write_text("off_diagonal: 3\n")
    inline = (2 * robotistic()).tolist()
    spec = {
        "default": {"off_diagonal": 0.5},
        "regions": {"street": "egoistic", "roi2": "plain.yaml", 3: inline},
    }
    stack = load_cost(write(tmp_path, spec))
    assert stack.shape == (5, N, N)
    assert torch.equal(stack[0], 0.5 * robotistic())
    assert torch.equal(stack[1], load_cost("egoistic"))
    assert torch.equal(stack[2], 3 * robotistic())
    assert torch.equal(stack[3], 2 * robotistic())
    assert torch.equal(stack[4], stack[0])  # sky: no entry, the default


def test_the_default_is_the_files_own_matrix_else_robotistic(tmp_path):
    own = load_cost(write(tmp_path, {"off_diagonal": 4, "regions": {"sky": "altruistic"}}))
    assert torch.equal(own[0], 4 * robotistic()) and torch.equal(own[4], load_cost("altruistic"))
    bare = load_cost(write(tmp_path, {"regions": {"sky": "altruistic"}}))
    assert torch.equal(bare[0], robotistic()) and torch.equal(bare[1], robotistic())


def test_a_defer_beside_regions_gives_every_matrix_a_row_and_a_regions_own_wins(tmp_path):
    spec = {
        "defer": 0.3,
        "regions": {"street": {"off_diagonal": 2, "defer": {"person": 0.1, "default": 0.7}}},
    }
    stack = load_cost(write(tmp_path, spec))
    assert stack.shape == (5, N + 1, N)
    assert torch.equal(stack[0, N], torch.full((N,), 0.3, dtype=torch.float64))
    street = torch.full((N,), 0.7, dtype=torch.float64)
    street[PERSON] = 0.1
    assert torch.equal(stack[1, N], street) and torch.equal(stack[1, :N], 2 * robotistic())


def test_save_cost_writes_a_stack_that_reads_back_exactly(tmp_path):
    stack = robotistic().expand(5, N, N).clone()
    stack[3, 2, 0] = 7.25
    stack = torch.cat([stack, torch.full((5, 1, N), 0.5, dtype=torch.float64)], 1)
    save_cost(tmp_path / "out.yaml", stack, "mine", header="certified for nothing")
    text = (tmp_path / "out.yaml").read_text()
    assert text.startswith("# certified for nothing\n")
    assert list(yaml.safe_load(text)["regions"]) == ["building"]  # only where it differs
    assert torch.equal(load_cost(tmp_path / "out.yaml"), stack)


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ({"regions": {"park": "egoistic"}}, "unknown region 'park': expected a RoI name"),
        ({"regions": {7: "egoistic"}}, "unknown region 7"),
        ({"regions": {"image": "egoistic"}}, "region 'image' is the whole image (RoI 0)"),
        ({"regions": {"street": "egoistic", 1: "altruistic"}}, "'street' and 1 are both RoI 1"),
        (
            {"regions": {"street": {"off_diagonal": 1, "defer": 0.2}}},
            "region 'street' has a 20x19 (a defer row) matrix and the default a 19x19 one",
        ),
        ({"regions": {"street": [[0, 1], [1, 0]]}}, "region 'street': an inline matrix is 19"),
        ({"regions": {"street": "nonsense"}}, "region 'street': unknown cost 'nonsense'"),
        ({"regions": {"street": "missing.yaml"}}, "region 'street': cost file not found"),
        (
            {"regions": {"street": {"off_diagonal": -1}}},
            "region 'street': cost matrix entry [0, 1] (predicted 'road', true 'sidewalk') is -1",
        ),
        ({"regions": {"street": 3}}, "region 'street' must be a preset's name"),
        ({"regions": {}}, "'regions' must map RoIs"),
        ({"default": "egoistic"}, "'regions' must map RoIs"),
        (
            {"default": "egoistic", "off_diagonal": 2, "regions": {"sky": "egoistic"}},
            "the default matrix is 'default' or the file's own key",
        ),
        ({"colour": 1, "regions": {"sky": "egoistic"}}, "unknown key 'colour'"),
    ],
)
def test_refusals_name_the_file_and_the_region_in_one_line(tmp_path, spec, message):
    path = write(tmp_path, spec)
    with pytest.raises((ValueError, FileNotFoundError)) as err:
        load_cost(path)
    text = str(err.value)
    assert text.startswith(f"cost file {path}: ") and message in text, text
    assert "\n" not in text


def test_a_regional_file_as_a_region_is_refused(tmp_path):
    write(tmp_path, {"regions": {"sky": "egoistic"}}, "inner.yaml")
    path = write(tmp_path, {"regions": {"street": "inner.yaml"}})
    with pytest.raises(ValueError, match=r"region 'street': inner\.yaml is a regional file itself"):
        load_cost(path)
