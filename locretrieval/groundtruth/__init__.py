"""groundtruth"""
