"""Recipes: schema and loader."""
from core.recipe.loader import LoadedRecipe, RecipeError, load_recipe
from core.recipe.schema import Recipe

__all__ = ["LoadedRecipe", "Recipe", "RecipeError", "load_recipe"]
