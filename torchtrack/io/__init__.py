"""Reading and writing: MOTChallenge text, the WPAFB truth CSV, frame sources, annotated videos, output folders
written as one set, and the data sets' locator and fetcher."""
