"""Specimen stores, one interface (`base`) over a folder (`folder`) and object storage (`s3`:
S3-compatible servers, its objects in `objects` and its build leases in `leases`); scratch folders
of exports, reports and builds (`scratch`)."""

__all__ = ["base", "folder", "leases", "objects", "s3", "scratch"]
