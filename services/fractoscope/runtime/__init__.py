"""What the three services share at run time: authentication (`auth`), bounded job pools (`jobs`),
the memory budget (`budget`), caches, request decoding, thread routing and process settings."""

__all__ = ["auth", "budget", "caches", "decoding", "jobs", "process", "threads"]
