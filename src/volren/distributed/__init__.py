"""Work beyond one process on Ray (an optional extra, ``pip install 'volren[ray]'``): batch rendering over workers
and sharded serving. Nothing here is imported unless ``--workers``, ``--ray-address``, ``volren batch`` or
``serve --shards`` asks for it, so the default path never loads Ray."""
