"""Collecting human-written instructions: a local web page, its JSON API and the variation pictures.

``demo-factory collect-instructions`` (``collect.cli``) serves ``collect.server``; instructions go to
a JSONL file through ``collect.store`` in the format ``demo_factory.instructions.human`` reads;
``collect.pictures`` renders what each variation asks for.
"""
