"""Object storage for specimens, uploads, jobs and build leases (S3-compatible servers)."""

from fractoscope.store.objects import Listed, ObjectMissing, PreconditionFailed, S3Objects, Stored, open_objects

__all__ = ["Listed", "ObjectMissing", "PreconditionFailed", "S3Objects", "Stored", "open_objects"]
