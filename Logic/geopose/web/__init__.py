"""``geopose view``: register a case and review it in the browser (a trame-slicer app).

Needs the ``web`` extra (``pip install -e ".[web]"``: trame-slicer with the slicer-core
wheel); the rest of the library never imports this package, and ``geopose view`` says
how to install it when it is missing. Layout: :mod:`.access` (where the server listens
and the token a page must present), :mod:`.session` (the inputs, the registration in a
worker thread with progress and Cancel, the review of a result folder), :mod:`.scene`
(the MRML nodes the views show), :mod:`.app` (the page), :mod:`.cli` (the command).
"""
