"""Object storage: ``s3://`` (and the other URLs obstore reaches) as a place for catalogs
and missions: stores opened from URLs with the usual credentials, objects read, written and
copied, folders mirrored."""

from standgrid.storage.objects import ObjectFolder, file_sha256, is_url

__all__ = ["ObjectFolder", "file_sha256", "is_url"]
