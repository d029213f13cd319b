"""trivla_drake.tasks"""
