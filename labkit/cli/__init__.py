"""The ``labkit`` command line (:mod:`.main`) and its subcommands (:mod:`.change`,
:mod:`.targets`) and output helpers (:mod:`.output`).
"""
