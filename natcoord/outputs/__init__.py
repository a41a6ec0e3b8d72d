"""What a run reports: channels of a case, reactions, the result record."""
