"""Target-based registration: sphere targets matched between scans (:mod:`.matching`),
the Helmert transformation (:mod:`.helmert`), poses (:mod:`.pose`), the network
of scans (:mod:`.network`) and the public entry (:mod:`.register`).
"""
