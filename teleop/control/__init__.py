"""The control numerics: wave variables (eq. 3), the codecs of the four LDR classes and the deadbands,
the passivity checks (eqs. 5, 8, 10, 11), transparency (eq. 7) and the rate cap.

The lowest layer above ``teleop.errors``/``teleop.limits``: pure functions of their inputs, no
clock, socket or file, and no import of any other ``teleop`` package.
"""
