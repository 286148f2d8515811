"""Defaults of what reading a store may hold in memory. A module of constants alone, so that the command
line can show them in its help without loading the store."""

DEFAULT_TILE_CACHE_MB = 512.0  # features and structure points of open tiles a query process keeps, MB
