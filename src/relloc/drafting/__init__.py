"""Team configs drafted and calibrated from recordings, below the command line.

:mod:`.team` decides a team from a bag (robots, UWB node mapping, reference, area; motion
capture found by message type), :mod:`.writer` writes the draft as commented TOML, and
:mod:`.calibrate` estimates pair biases and heading offsets from a recording with motion capture
and writes them into a config's text, comments kept (``relloc init``, ``relloc calibrate``).
"""
