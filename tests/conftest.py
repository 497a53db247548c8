"""Shared by the test folders: pytest puts this folder on ``sys.path``, so helper modules here
(``_track_decode``) can be imported by tests in any subfolder."""
