"""The gymnasium environments (their own room: they read the view caches of search/data, which the search room
itself never imports). Registered ids: uavsearch/envs.py; manuals: the class docstrings of search_env.py
(ActiveSearchEnv, WideSearchEnv) and vector_env.py (SearchVectorEnv)."""
