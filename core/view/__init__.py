"""The operator web view: a live page of the line and a review page over a results store."""
