"""Object storage for specimens, uploads, jobs and build leases (S3-compatible servers)."""
