"""The order probe: colour mentions found by their names, and a probe that reads the press from a colour word."""

import pytest

from demo_factory.tools.order_probe import colour_mentions, main, probe_table


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
