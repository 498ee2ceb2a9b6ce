"""Learning task types: ``lerobot.dataset`` and ``lerobot.train`` (LeRobot; extra ``learn``)."""
