"""``pixelmpc tune``: the search against the speed frontier (``search``), the searched settings (``space``) and what
the search writes (``report``)."""
