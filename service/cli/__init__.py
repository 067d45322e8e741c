"""The command line: `polydda` (:mod:`.main`: the parser and entry point; the commands in
:mod:`.scenes`, :mod:`.runs`, :mod:`.analyses`, :mod:`.results`, :mod:`.remote`, sharing
:mod:`.common`) and the small REST client it submits scenes with (:mod:`.client`)."""
