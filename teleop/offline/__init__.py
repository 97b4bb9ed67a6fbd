"""What runs without a network: ``teleop sim``, the sweep and the experiment, the log reader and the
report with its plots. Imports the session and the layers below it, never ``transport``.
"""
