"""One object per task (`task._target_` in conf/task/*.yaml): what render, preprocess, train, eval and
summary mean for it. `src/stages.py` calls these and holds no task-specific code."""
