"""The lab's side of a cohort: find its knees, submit them to a server and bring the results home
(``submit``), compare two results of one knee (``compare``), and one HTML page over a cohort tree
(``report``)."""
