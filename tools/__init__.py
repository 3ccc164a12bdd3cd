"""Development tools of the source tree, run from the project root (not installed with thermbench):

    python -m tools.confref   # docs/configuration.md from conf/
    python -m tools.nbrun     # the guided notebooks in notebooks/, headless

The ``thermbench`` package never imports them.
"""
