"""File formats: the raw-trial contract, the canonical dataset and armfit's artifacts."""


__all__: list[str] = []
