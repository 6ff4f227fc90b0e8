"""omnidl.data"""
