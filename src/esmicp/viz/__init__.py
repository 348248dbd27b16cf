"""Pictures of a registration, built on the solver's per-iteration callback (the solver never plots).

Needs the ``viz`` extra (``pip install 'esmicp[viz]'``: matplotlib and plotly), imported only when a
picture is drawn. Every function returns the figure object (a matplotlib ``Figure`` or
``FuncAnimation``, a plotly ``Figure``), for notebooks; the ``write_*`` helpers save them atomically.
"""
