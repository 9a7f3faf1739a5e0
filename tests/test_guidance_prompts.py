"""Prompt augmentation/validation, negative-prompt parsing and similarity-based exclusion."""

from __future__ import annotations

import logging

import pytest
import torch

from nerfart_plugin.errors import ConfigError, DataError
from nerfart_plugin.guidance import (NegativeSampler, ToyGuidance, augment_prompt, default_source_prompt,
    load_negatives, validate_prompt)
from nerfart_plugin.guidance.prompts import package_negatives_path, parse_negative_prompts

OFFICIAL = "negative_prompts_official.txt"


@pytest.fixture
def official_path(request):
    from pathlib import Path

    p = Path(__file__).resolve().parents[2] / "shared" / "data" / OFFICIAL
    if not p.is_file():
        pytest.skip(f"{p} not available")
    return p


def test_augment_prompt() -> None:
    assert augment_prompt("Vincent van Gogh") == "painting, oil on canvas, Vincent van Gogh self-portrait style"
    assert augment_prompt("  vincent VAN gogh ") == augment_prompt("Vincent van Gogh")
    for name in ("Fauvism", "Edvard Munch", "Fernando Botero"):
        out = augment_prompt(name.upper())
        assert out.startswith("painting, oil on canvas, ") and name in out
    assert augment_prompt("a bronze statue") == "a bronze statue"


def test_source_prompt_and_validation() -> None:
    assert default_source_prompt("person") == "a photo of a person"
    assert default_source_prompt("object") == "a photo"  # a masked object is not a person
    assert default_source_prompt("scene") == "a photo"
    with pytest.raises(ConfigError):
        default_source_prompt("panorama")
    assert validate_prompt("  Fauvism ") == "Fauvism"
    for bad in ("", "   \t\n", None):
        with pytest.raises(ConfigError, match="prompt"):
            validate_prompt(bad)


def test_parse_official_file(official_path) -> None:
    pairs = parse_negative_prompts(official_path.read_text(encoding="utf-8"))
    assert len(pairs) == 131
    assert pairs[0] == ("base", "human")
    assert pairs[-1] == ("portrait", "Self-Portrait by Van Gogh")
    assert len(load_negatives(official_path)) == 131


def test_parse_is_robust() -> None:
    text = "\ufeff#a\r\n1.sketch\r\n\r\n3. pencil  drawing \r\nno number\r\n2)Sketch\r\n#b\r\n4.\r\n5.zombie\r\n"
    expected = [("a", "sketch"), ("a", "pencil drawing"), ("a", "no number"), ("b", "zombie")]
    assert parse_negative_prompts(text) == expected
    assert len(parse_negative_prompts(text, dedupe=False)) == 5


def test_package_list(official_path) -> None:
    assert package_negatives_path().is_file()
    pkg = load_negatives()
    assert 190 <= len(pkg) <= 230
    assert len({p.lower() for p in pkg}) == len(pkg)
    assert set(load_negatives(official_path)) <= set(pkg)
    for p in ("Ukiyo-e", "Cubism", "Pop art", "Pixar character", "Marble statue", "zombie"):
        assert p in pkg


def test_load_negatives_errors(tmp_path) -> None:
    with pytest.raises(DataError, match="missing.txt"):
        load_negatives(tmp_path / "missing.txt")
    empty = tmp_path / "empty.txt"
    empty.write_text("#only a header\n\n")
    with pytest.raises(DataError, match="no prompts"):
        load_negatives(empty)


def test_negative_exclusion_by_similarity(caplog: pytest.LogCaptureFixture) -> None:
    g = ToyGuidance()
    negs = ["red", "blue", "a red car", "Ukiyo-e", "green"]
    with caplog.at_level(logging.INFO):
        s = NegativeSampler(g, negs, "red", threshold=0.8, num_per_step=2)
    assert [n for n, _ in s.excluded] == ["red", "a red car"]
    assert s.prompts == ["blue", "Ukiyo-e", "green"]
    assert "excluded 2" in caplog.text and "'a red car'" in caplog.text
    p1, e1 = s.sample(torch.Generator().manual_seed(3))
    p2, e2 = s.sample(torch.Generator().manual_seed(3))
    assert p1 == p2 and len(p1) == 2 and e1.shape == (2, g.embed_dim) and torch.equal(e1, e2)
    assert set(p1) <= set(s.prompts)
    all_p, all_e = NegativeSampler(g, negs, "red", num_per_step=None).sample()
    assert len(all_p) == all_e.shape[0] == 3
    with pytest.raises(ConfigError, match="threshold"):
        NegativeSampler(g, ["red"], "red")


def test_exclusion_by_meaning() -> None:
    """Negatives that depict the target itself are dropped by meaning, whatever their embedding score."""
    from nerfart_plugin.guidance.prompts import exclusion_reason

    vg_raw, vg = "Vincent van Gogh", augment_prompt("Vincent van Gogh")
    for neg, cat in [("Vincent van Gogh", "artists"), ("Self-Portrait by Van Gogh", "portrait"),
                     ("Oil painting", "painting_styles"), ("Mona Lisa by Leonardo da Vinci", "portrait")]:
        assert exclusion_reason(neg, cat, [vg, vg_raw]) is not None, neg
    for neg, cat in [("Edvard Munch", "artists"), ("Cubism", "painting_styles"), ("Pixar character", "characters")]:
        assert exclusion_reason(neg, cat, [vg, vg_raw]) is None, neg  # other styles stay negatives
    assert "joker" in exclusion_reason("The Joker", "characters", ["joker"])
    assert "pixar" in exclusion_reason("Pixar character", "characters", ["Pixar"])
    assert "#disney" in exclusion_reason("disney princess", "disney", ["a Pixar movie"])  # category rule
    assert "#zombie" in exclusion_reason("female zombie", "zombie", ["Zombie"])
    assert exclusion_reason("Batman", "characters", ["Tolkien Elf"]) is None


def test_sampler_logs_and_records_reasons(caplog: pytest.LogCaptureFixture) -> None:
    from nerfart_plugin.guidance.prompts import load_negative_pairs

    g = ToyGuidance()
    target = augment_prompt("Vincent van Gogh")
    with caplog.at_level(logging.INFO):
        s = NegativeSampler(g, load_negative_pairs(), target, threshold=1.0, raw_prompt="Vincent van Gogh")
    excluded = dict(s.excluded)
    assert "Vincent van Gogh" in excluded and "Self-Portrait by Van Gogh" in excluded
    assert all(isinstance(r, str) and r for r in excluded.values())
    assert "'Self-Portrait by Van Gogh' (" in caplog.text
    assert "Edvard Munch" in s.prompts and "Vincent van Gogh" not in s.prompts


def test_negative_sources(tmp_path, official_path) -> None:
    from nerfart_plugin.guidance.prompts import resolve_negatives

    g = ToyGuidance()
    assert len(resolve_negatives("official", g, "Joker")) == 131
    assert resolve_negatives("official", g, "Joker") == parse_negative_prompts(official_path.read_text(encoding="utf-8"))
    assert len(resolve_negatives("auto", g, "Joker")) == len(resolve_negatives("package", g, "Joker")) > 190
    user = tmp_path / "mine.txt"
    user.write_text("#mine\n1.cubism\n2.a wax figure\n", encoding="utf-8")
    assert resolve_negatives(str(user), g, "Joker") == [("mine", "cubism"), ("mine", "a wax figure")]
    with pytest.raises(DataError, match="stylize.negatives"):
        resolve_negatives(str(tmp_path / "absent.txt"), g, "Joker")
