"""svolsdf.prior"""
