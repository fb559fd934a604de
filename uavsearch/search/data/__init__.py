"""Data for the search: rendered view sets (shards in a store) and the view caches of perception outputs."""
