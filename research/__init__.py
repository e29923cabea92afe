"""Diagnostics written to answer one question each about warpavatar's fits, kept apart from the product.

Run one from the repository root as ``python -m research.<name> --help``; ``research/README.md`` says what each
answers. They build on the product (``warpavatar``) and on the maintained tools (``tools/``); nothing under
``warpavatar/`` imports them.
"""
