"""The order probe: colour mentions found by their names, and a probe that reads the press from a colour word."""

import pytest

from demo_factory.instructions import COLOUR_SYNONYMS
from demo_factory.tasks.palette import COLOURS
from demo_factory.tools.order_probe import colour_mentions, main, probe_table, sentence_sets


def test_colour_mentions_label_each_colour_with_its_press_wherever_it_stands():
    text = "Wrap up with navy, once red and then dark green have gone down."
    assert [(text[a:b], press) for a, b, press in colour_mentions(text, ("red", "green", "navy"))] == [
        ("navy", 2), ("red", 0), ("dark green", 1)]
    assert colour_mentions("press the grey one", ("gray",)) == [(10, 14, 0)]
    assert colour_mentions("press the darker blue one, then red", ("navy", "red")) is None  # not a name it knows


def test_token_position_reads_the_press_better_than_the_commonest_one_on_phrasings_never_seen():
    commonest, position = probe_table("push_buttons", ["position"])
    assert position["encoder"] == "position" and commonest["colour words"]["held-out phrasings"] > 1000
    assert position["held-out phrasings"] > commonest["held-out phrasings"] + 0.15
    assert position["human"] > commonest["human"] + 0.3


def test_order_probe_rejects_an_unknown_encoder(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--encoder", "bert"])
    assert exit_info.value.code == 2 and "invalid choice: 'bert'" in capsys.readouterr().err


def test_colour_target_labels_the_corrupted_splits_renamed_colours_with_their_palette_colour():
    sets = sentence_sets("push_buttons", "colour")
    sentence, mentions = sets["corrupted"][0]
    assert set(sets) == {"train", "held-out phrasings", "corrupted", "human"} and len(sets["corrupted"]) > 100
    renamed = {COLOUR_SYNONYMS[name]: i for i, name in enumerate(COLOURS)}
    assert [renamed[sentence[a:b].lower()] for a, b, _ in mentions] == [label for *_, label in mentions]
    trained = {label for _, m in sets["train"] for *_, label in m}
    assert {label for _, m in sets["corrupted"] for *_, label in m} <= trained
