"""Authenticated, authorised Zenoh for a team: a private CA, certificates and role configs.

The derivation: docs/explanation/internals.md, section ``relloc.live.secure``.
"""
