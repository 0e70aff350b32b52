"""svolsdf.field"""
