"""What is done with a trained :class:`s3k.detector.Detector`: metrics (pure), evaluate and its report,
predict, track, stream and export. Every module here reads frames through the detector."""
