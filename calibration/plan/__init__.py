"""Campaign planning: the poses the tracker sees and the arm reaches, chosen for what the
campaign must pin down, in travel order, written as controller programs with a report.
"""
